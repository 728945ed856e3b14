"""The honest side of tests/test_cecb_fuzz.py's bus: nodes that follow docs/protocol.md (as far
as a CAN-ECB can tell), and the ledger of who holds which TxNode and etag.

``Honest`` is a node reduced to what the CAN-ECB sees of it: it knocks, answers Census and Query
with its Stage frames, claims its Offer, binds channels (SUB_BIND, PUB_BIND, PUB_BIND(c)),
follows the contradiction rule, answers Hello (CLAIM, SUB_AT, PUB_AT, DECLARE), moves on an
Assign, unsubscribes, declares and asks for the roster. It hears only the CAN-ECB's frames (the
forger's go to the CAN-ECB alone): the machine tests the CAN-ECB, and these nodes are how it
reaches deep states, not what it checks.

``Ledger`` keeps, for TxNodes (or etags), the holder the CAN-ECB last gave each one, on the wire
(Assign, Bind) or in its tables; a key handed to a second holder while the first still holds it
is the fault the machine looks for. A holder given another key frees its old one (a move).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from ups import _canproto as p
from ups import _cantransfer as t

Frame = p.Management


@dataclass
class Chan:
    sub: bool = False
    pub: bool = False
    cls: int = 0  #: the size class its events need (a publisher's)
    etag: int | None = None  #: the etag it relies on
    asked: bool = False  #: a request is out, not answered yet


@dataclass
class Honest:
    node_id: int
    txnode: int | None = None
    joining: bool = False
    chans: dict[int, Chan] = field(default_factory=dict)
    declared: dict[int, p.Declare] = field(default_factory=dict)  #: etag -> its DECLARE

    @property
    def nibbles(self) -> tuple[int, ...]:
        return p.nibbles_of(self.node_id)

    def forget(self) -> None:
        """What a node that starts again knows: nothing (it joins anew)."""
        self.txnode, self.joining, self.declared = None, False, {}
        for ch in self.chans.values():
            ch.etag, ch.asked = None, False

    # --- what the node does on its own ---------------------------------------------------

    def join(self) -> list[Frame]:
        if self.txnode is not None:
            return []
        self.joining = True
        return [p.Knock()]

    def request(self, uid: int) -> list[Frame]:
        ch = self.chans[uid]
        if self.txnode is None:
            return []
        ch.asked = True
        if ch.sub:
            return [p.Request(p.SUB_BIND, self.txnode, uid)]
        return [p.Request(p.PUB_BIND, self.txnode, uid, ch.cls)]

    def use(self, uid: int, *, sub: bool, cls: int = 0) -> list[Frame]:
        ch = self.chans.setdefault(uid, Chan())
        if sub:
            ch.sub = True
        else:
            ch.pub, ch.cls = True, max(ch.cls, cls)
        if self.txnode is None:
            return []
        if ch.etag is None:
            return self.request(uid)
        if not sub and t.size_class(ch.etag) < ch.cls:  # a larger class: move the channel
            ch.asked = True
            return [p.Request(p.PUB_BIND, self.txnode, uid, ch.cls)]
        return [p.Holds(not sub, self.txnode, ch.etag, uid)]

    def unsubscribe(self, uid: int) -> list[Frame]:
        ch = self.chans.get(uid)
        if ch is None or not ch.sub or self.txnode is None:
            return []
        ch.sub = False
        if not ch.pub:
            del self.chans[uid]
        return [p.Request(p.UNSUB, self.txnode, uid)]

    def retry(self) -> list[Frame]:
        """The request retry: what is out and unanswered goes again."""
        if self.joining:
            return [p.Knock()]
        out: list[Frame] = []
        for uid, ch in self.chans.items():
            if self.txnode is not None and (ch.asked or ch.etag is None):
                out += self.request(uid)
        return out

    def declare(self, uid: int, size: int, period: int, deadline: int, jitter: int) -> list[Frame]:
        ch = self.chans.get(uid)
        if ch is None or not ch.pub or ch.etag is None or self.txnode is None:
            return []
        if ch.etag >= p.LARGE_FIRST_ETAG:
            size = max(1, size)
        msg = p.Declare(self.txnode, ch.etag, min(size, 8), period, deadline, jitter)
        self.declared[ch.etag] = msg
        return [msg]

    def roster(self) -> list[Frame]:
        return [] if self.txnode is None else [p.Roster(self.txnode, 0)]

    def announce(self) -> list[Frame]:
        """The answer to Hello, or to an Assign of its own id once joined."""
        assert self.txnode is not None
        out: list[Frame] = [p.Request(p.CLAIM, self.txnode, self.node_id)]
        for uid, ch in self.chans.items():
            if ch.etag is not None:
                if ch.sub:
                    out.append(p.Holds(False, self.txnode, ch.etag, uid))
                if ch.pub:
                    out.append(p.Holds(True, self.txnode, ch.etag, uid))
        out += [
            p.Declare(self.txnode, d.etag, d.size_bytes, d.period, d.deadline, d.jitter)
            for d in self.declared.values()
        ]
        return out

    # --- what it hears from the CAN-ECB ----------------------------------------------------

    def hear(self, msg: Frame) -> list[Frame]:
        if isinstance(msg, p.Hello):
            return (
                self.announce() if self.txnode is not None else self.join() if self.joining else []
            )
        if isinstance(msg, p.Census | p.Query) and self.joining:
            first = 0 if isinstance(msg, p.Census) else len(msg.prefix)
            if isinstance(msg, p.Query) and self.nibbles[:first] != msg.prefix:
                return []
            return [p.Stage(msg.epoch, s, self.nibbles[s]) for s in range(first, p.NIBBLES)]
        if isinstance(msg, p.Offer) and msg.node_id == self.node_id and self.joining:
            return [p.Request(p.CLAIM, msg.txnode, self.node_id)]
        if isinstance(msg, p.Assign) and msg.node_id == self.node_id:
            was, self.txnode, self.joining = self.txnode, msg.txnode, False
            if was is None:  # joined: a node that joins starts with nothing at the CAN-ECB
                self.declared = {}
                for ch in self.chans.values():
                    ch.etag, ch.asked = None, False
                return [f for uid in self.chans for f in self.request(uid)]
            if was != msg.txnode:
                self.declared = {}
            return self.announce()
        if isinstance(msg, p.Bind):
            return self.bound(msg)
        if isinstance(msg, p.RosterEnd) and msg.txnode == self.txnode and not msg.done:
            return [p.Roster(msg.txnode, msg.next)]
        return []

    def bound(self, msg: p.Bind) -> list[Frame]:
        """A Bind of the CAN-ECB: an answer, or a contradiction (docs/protocol.md)."""
        out: list[Frame] = []
        again = [
            u for u, ch in self.chans.items()
            if ch.etag is not None and (ch.etag == msg.etag) != (u == msg.uid)
        ]  # fmt: skip
        for uid in again:  # contradicted: rely on neither, ask again
            self.chans[uid].etag = None
            self.declared.pop(msg.etag, None)
            out += self.request(uid)
        ch = self.chans.get(msg.uid)
        if ch is None or msg.uid in again or not ch.asked or self.txnode is None:
            return out
        if ch.pub and t.size_class(msg.etag) < ch.cls:  # too small for its events: move it
            return [*out, p.Request(p.PUB_BIND, self.txnode, msg.uid, ch.cls)]
        ch.etag, ch.asked = msg.etag, False
        if ch.sub and ch.pub:
            out.append(p.Holds(True, self.txnode, msg.etag, msg.uid))
        return out


Excuse = Callable[[int, int, int], str | None]


class Ledger:
    """Key (TxNode or etag) -> the holder (node id or UID) the CAN-ECB gave it last."""

    def __init__(self, what: str) -> None:
        self.what = what
        self.holder: dict[int, int] = {}
        #: pairs a forger reported (CLAIM, SUB_AT, PUB_AT): a CAN-ECB may adopt them in a
        #: recovery window (docs/protocol.md, Restarts), and the real holder then moves
        self.forged: set[tuple[int, int]] = set()

    def see(self, pairs: list[tuple[int, int, str]], excuse: Excuse) -> None:
        """What one call of the CAN-ECB said, at once: (key, holder, where) from its frames,
        then its tables. One call's frames are queued together and leave lowest identifier
        first, as CAN arbitration would send them anyway: a holder's move (a channel to a
        larger class) and the reuse of the key it left may come in either order, and a pair
        that a later one of the same call supersedes (the holder moves on) is a step between.
        So each holder's last pair counts; a step between may take only a free key, its own,
        or one whose holder moves in the same call."""
        last: dict[int, tuple[int, str]] = {}
        for key, holder, where in pairs:
            last[holder] = (key, where)
        for key, holder, where in pairs:
            prior = self.holder.get(key)
            if last[holder][0] != key and prior not in (None, holder) and prior not in last:
                self.check(key, prior, holder, where, excuse)
        for k in [k for k, h in self.holder.items() if h in last and last[h][0] != k]:
            del self.holder[k]  # it moved: its old key is free
        for holder, (key, where) in last.items():
            prior = self.holder.get(key)
            if prior is not None and prior != holder:
                self.check(key, prior, holder, where, excuse)
                for k in [k for k, h in self.holder.items() if h == holder]:
                    del self.holder[k]
            self.holder[key] = holder

    def check(self, key: int, prior: int, holder: int, where: str, excuse: Excuse) -> None:
        if (key, prior) in self.forged or (key, holder) in self.forged:
            return
        assert excuse(key, prior, holder) is not None, (
            f"{where}: {self.what} {key:#x} handed to {holder:#x} while {prior:#x} holds it"
        )

    def drop(self, keep: Callable[[int, int], bool]) -> None:
        self.holder = {k: h for k, h in self.holder.items() if keep(k, h)}
