"""The CAN fuzzer's frame generator (see :mod:`benchmarks.can_fuzz`).

The generator (``FrameGen``) mixes:

(a) fully random 29-bit identifiers with 0-8 random bytes;
(b) 11-bit data frames, remote frames (both formats) and error frames;
(c) semi-valid management frames: ``ups._canproto.encode`` of every frame class filled with
    random field values in range, the same with the data length mutated (truncated or padded)
    or one byte flipped;
(d) events on random etags from random TxNodes.

Values in (c) and (d) are drawn, part of the time, from the scenario's own (``Targets``): the
etags and UIDs of the channels under test (``--aim``, 0.1 of the time) and the TxNodes of the
real nodes (half the time), so that forged Binds and reports hit what is in use. Three
exclusions keep the verdicts meaningful:

- No forged event ever carries a real node's TxNode (CAN has no authentication: such a frame
  *is* that node publishing). So every event from a real node's TxNode is a real publication,
  and the subscribers check its payload: any other payload is a wrong delivery. Forged events
  from other TxNodes on the channels' etags are generated and are counted as ``forged``, not
  checked, except on ``Targets.protected`` etags (channels forwarded to TCP, where the source
  TxNode is no longer visible), where none is generated.
- Frames sent from a real node's TxNode (requests, SUB_AT/PUB_AT, DECLARE) never name a
  channel under test, and Assign never names a real node id: again, that would be the node (or
  its CAN-ECB) speaking, not a stray frame.
- Hello carries the CAN-ECB's own instance or a higher one, and Serving only its own: by
  docs/protocol.md a Serving of a lower instance (or any Serving while it is a candidate, which
  the flood itself makes it by its Hellos) makes the CAN-ECB stand by, until it takes over
  again 4 s after such frames stop. ``--rivals`` lifts this.
"""

from __future__ import annotations

import collections
import random
from collections.abc import Callable
from dataclasses import dataclass, field

import can

from ups import _canproto as p
from ups._errors import DecodeError

U64 = (1 << 64) - 1
#: the CAN-ECB's offer of a TxNode to a joiner, where the codec has it
_OFFER: Callable[[int, int], p.Management] | None = getattr(p, "Offer", None)


@dataclass
class Targets:
    """What the generator aims at besides uniformly random values."""

    etags: list[int]  #: etags of the channels under test
    uids: list[int]  #: their UIDs
    txnodes: set[int]  #: TxNodes of the real nodes: never the sender of a forged event
    instance: int  #: the CAN-ECB's instance
    protected: set[int] = field(default_factory=set)  #: etags without any forged event
    rivals: bool = False  #: Hello/Serving of any instance (see the module's docstring)
    aim: float = 0.1  #: how often an etag or UID field gets one under test
    aim_txnode: float = 0.5  #: how often a management frame's TxNode is a real node's


def classify(msg: can.Message) -> str:
    """What a receiver following docs/protocol.md makes of ``msg``."""
    if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id or msg.is_fd:
        return "foreign"
    can_id = msg.arbitration_id
    if not p.is_management(can_id):
        return "event"
    try:
        decoded = p.decode(can_id, bytes(msg.data))
    except DecodeError:
        return "malformed"
    except Exception:  # the codec itself failed: a bug the test reports
        return "crash"
    if isinstance(decoded, p.ECB_FRAMES):
        return "ecb_frame"
    if isinstance(decoded, p.Request | p.Holds | p.Declare):
        return "node_request"
    return "joiner"


class FrameGen:
    """Seeded frames of the four families; ``counts`` tallies them by ``classify``, ``kinds``
    by how they were built."""

    def __init__(self, seed: int, targets: Targets) -> None:
        self.rng = random.Random(seed)
        self.t = targets
        self._foreign_tx = [t for t in range(p.TXNODE_COUNT) if t not in targets.txnodes]
        self.counts: collections.Counter[str] = collections.Counter()
        self.kinds: collections.Counter[str] = collections.Counter()
        self.samples: dict[str, can.Message] = {}  # the first frame of each category

    def __iter__(self) -> FrameGen:
        return self

    def __next__(self) -> can.Message:
        r = self.rng.random()
        if r < 0.25:
            msg = self._tame(self._random_frame())
        elif r < 0.35:
            msg = self._foreign_frame()
        elif r < 0.75:
            msg = self._tame(self._management_frame())
        else:
            msg = self._event_frame()
        category = classify(msg)
        self.counts[category] += 1
        self.samples.setdefault(category, msg)
        return msg

    def _tame(self, msg: can.Message) -> can.Message:
        """Unless ``rivals``: a Serving of another instance, or a Hello of a lower one (made by
        a mutation or by chance), becomes the CAN-ECB's own. Draws nothing from the generator,
        so that a seed gives the same frames whatever the CAN-ECB's instance."""
        if self.t.rivals or classify(msg) != "ecb_frame":
            return msg
        decoded = p.decode(msg.arbitration_id, bytes(msg.data))
        if isinstance(decoded, p.Serving) and decoded.instance != self.t.instance:
            decoded = p.Serving(self.t.instance)
        elif isinstance(decoded, p.Hello) and decoded.instance < self.t.instance:
            decoded = p.Hello(self.t.instance)
        else:
            return msg
        self.kinds["tamed"] += 1
        return _frame(*p.encode(decoded))

    # values ---------------------------------------------------------------------------------

    def _txnode(self) -> int:
        """A TxNode for a management frame: a real node's half the time."""
        if self.t.txnodes and self.rng.random() < self.t.aim_txnode:
            return self.rng.choice(sorted(self.t.txnodes))
        return self.rng.randrange(p.TXNODE_COUNT)

    def _etag(self) -> int:
        if self.t.etags and self.rng.random() < self.t.aim:
            return self.rng.choice(self.t.etags)
        return self.rng.randint(p.FIRST_ETAG, p.LAST_ETAG)

    def _uid(self, txnode: int | None = None) -> int:
        """A UID; one under test at times (``aim``), unless ``txnode`` is a real node's."""
        real_sender = txnode is not None and txnode in self.t.txnodes
        if self.t.uids and not real_sender and self.rng.random() < self.t.aim:
            return self.rng.choice(self.t.uids)
        return self.rng.getrandbits(64)

    def _instance(self) -> int:
        """Any instance if ``rivals``; else the CAN-ECB's own half the time, or a higher one."""
        own, bits, coin = self.t.instance, self.rng.getrandbits(64), self.rng.random()
        if self.t.rivals:
            return bits
        return own if coin < 0.5 else own + bits % (U64 - own + 1)

    def _event_id(self, priority: int, txnode: int, etag: int) -> int:
        """An event identifier from a TxNode no real node holds, off the protected etags."""
        if txnode in self.t.txnodes:
            txnode = self.rng.choice(self._foreign_tx)
        while etag in self.t.protected:
            etag = self.rng.randint(p.FIRST_ETAG, p.LAST_ETAG)
        return p.make_id(priority, txnode, etag)

    # (a) ------------------------------------------------------------------------------------

    def _random_frame(self) -> can.Message:
        can_id = self.rng.getrandbits(29)
        if not p.is_management(can_id):
            can_id = self._event_id(*p.split_id(can_id))
        self.kinds["random"] += 1
        return _frame(can_id, self.rng.randbytes(self.rng.randint(0, 8)))

    # (b) ------------------------------------------------------------------------------------

    def _foreign_frame(self) -> can.Message:
        rng = self.rng
        choice = rng.randrange(4)
        self.kinds[("std", "remote_std", "remote_ext", "error")[choice]] += 1
        if choice == 0:
            data = rng.randbytes(rng.randint(0, 8))
            return can.Message(arbitration_id=rng.getrandbits(11), data=data, is_extended_id=False)
        if choice in (1, 2):
            extended = choice == 2
            return can.Message(
                arbitration_id=rng.getrandbits(29 if extended else 11),
                is_extended_id=extended,
                is_remote_frame=True,
                dlc=rng.randint(0, 8),
            )
        return can.Message(arbitration_id=rng.getrandbits(29), is_error_frame=True, dlc=0)

    # (c) ------------------------------------------------------------------------------------

    def _management(self) -> p.Management:
        rng = self.rng
        builders: list[Callable[[], p.Management]] = [
            lambda: p.Stage(rng.randrange(16), rng.randrange(16), rng.randrange(16)),
            lambda: p.Query(
                rng.randrange(16), tuple(rng.randrange(16) for _ in range(rng.randint(1, 15)))
            ),
            lambda: p.Census(rng.randrange(16)),
            p.Knock,
            lambda: p.Assign(self._txnode(), rng.getrandbits(64)),  # never a real node's id
            *([lambda: _OFFER(self._txnode(), rng.getrandbits(64))] if _OFFER else []),
            lambda: p.Hello(self._instance()),
            lambda: p.Serving(rng.getrandbits(64) if self.t.rivals else self.t.instance),
            lambda: p.Bind(self._etag(), self._uid()),
            lambda: p.Failed(self._uid()),
            lambda: p.Limit(self._txnode(), self._uid()),
            lambda: p.TxNodesFull(rng.getrandbits(64)),
            lambda: p.EtagsFull(self._uid()),
            lambda: p.Grant(self._etag(), self._txnode(), rng.randrange(256)),
            lambda: p.Refuse(
                self._etag(), self._txnode(), self._etag(), self._txnode(), rng.randrange(1 << 16)
            ),
            *(self._request(kind) for kind in (p.PUB_BIND, p.SUB_BIND, p.UNSUB, p.CLAIM)),
            self._holds,
            self._declare,
        ]
        return rng.choice(builders)()

    def _request(self, kind: int) -> Callable[[], p.Management]:
        def build() -> p.Management:
            txnode = self._txnode()
            value = self.rng.getrandbits(64) if kind == p.CLAIM else self._uid(txnode)
            return p.Request(kind, txnode, value)

        return build

    def _holds(self) -> p.Management:
        txnode = self._txnode()
        return p.Holds(self.rng.random() < 0.5, txnode, self._etag(), self._uid(txnode))

    def _declare(self) -> p.Management:
        rng = self.rng
        return p.Declare(
            self._txnode(), self._etag(), rng.randint(0, 8), rng.randint(1, 0xFFFF),
            rng.randint(1, 0xFFFF), rng.randrange(256),
        )  # fmt: skip

    def _management_frame(self) -> can.Message:
        msg = self._management()
        can_id, data = p.encode(msg)
        kind = type(msg).__name__
        if isinstance(msg, p.Request):
            kind = {p.PUB_BIND: "PUB_BIND", p.SUB_BIND: "SUB_BIND", p.UNSUB: "UNSUB"}.get(
                msg.kind, "CLAIM"
            )
        r = self.rng.random()
        if r < 0.2:  # the table's length, mutated: truncated or padded
            length = self.rng.choice([n for n in range(9) if n != len(data)])
            data = data[:length] + self.rng.randbytes(max(0, length - len(data)))
            kind += "/length"
        elif r < 0.3 and data:  # one byte flipped
            i = self.rng.randrange(len(data))
            data = data[:i] + bytes([data[i] ^ self.rng.randint(1, 255)]) + data[i + 1 :]
            kind += "/flipped"
        self.kinds[kind] += 1
        return _frame(can_id, data)

    # (d) ------------------------------------------------------------------------------------

    def _event_frame(self) -> can.Message:
        rng = self.rng
        can_id = self._event_id(rng.randint(2, 255), rng.randrange(p.TXNODE_COUNT), self._etag())
        self.kinds["event"] += 1
        return _frame(can_id, rng.randbytes(rng.randint(0, 8)))


def _frame(can_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=True)
