"""A node's TCP inbox: the listening socket and the links on which publishers deliver events.

It counts what never arrives (sequence numbers per publisher and channel, see docs/protocol.md)
and, with TLS, accepts the events of a channel only from the nodes the TCP-ECB says publish on
it, each with its identity (``vouch``, from its ``Publishers`` frames). A link whose event (or
Start) is not vouched for yet is held, unread, until the ECB's word comes; after
``VOUCH_WAIT`` seconds without it the link is cut off and what it held is counted
(``unvouched``). A link whose node the ECB vouched for on no channel counts as waiting at the
doorman: it is closed after 5 s, evicted first when too many wait, and reads no frame larger
than its own 16 KiB buffer. The links' receive buffers grow from one budget (``_tcpbounds``).

A Start of a channel the node does not subscribe to, while it watches patterns, is held the
same way, up to ``NAMES_WAIT`` seconds, for the TCP-ECB's Names (``named``): the ECB puts a
pattern subscriber on a newly named channel's lists before it tells the node the name, and the
publisher's Start may come first. Once the name comes, the channel has joined the pattern's
subscriptions and its events are delivered from the first; if it does not, the link goes on
and the channel's events are counted as ``unsubscribed``.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING, Any

from . import _tcpwire as w
from ._statuspacer import StatusGate
from ._tcpbounds import Doorman
from ._tcplink import HELD, Link
from ._tls import identity

if TYPE_CHECKING:
    from ._face import ChannelState, Deliver

log = logging.getLogger("ups.tcp")

MAX_PUBLISHERS = 1024  #: links from publishers a node accepts at once
VOUCH_WAIT = 5.0  #: seconds a link may wait for the ECB to vouch for its publisher
NAMES_WAIT = 1.0  #: seconds a Start of a channel not subscribed to waits for the ECB's Names
_UNNAMED = 1024  #: channels a link remembers having waited for in vain (then it forgets them)

_HeldEvent = tuple[int, bytes, int, int]


class _Publisher:
    """The other side of one incoming link: who says it is, and who its certificate says."""

    __slots__ = (
        "allowed", "awaiting", "expected", "held", "identity", "node_id", "timer", "unnamed",
    )  # fmt: skip

    def __init__(self, node_id: int, identity: str | None, expected: dict[int, int]) -> None:
        self.node_id = node_id
        self.identity = identity
        self.expected = expected  # uid -> the number expected next: the inbox's, for node_id
        self.allowed: set[int] = set()  # channels vouched for on this link, for its lifetime
        self.held: list[_HeldEvent | w.Start] | None = None  # read while waiting for a voucher
        self.timer: asyncio.TimerHandle | None = None
        self.awaiting: int | None = None  # held for this channel's name (None: for a voucher)
        self.unnamed: set[int] = set()  # channels whose names were waited for in vain


class Inbox:
    """Links from publishers. ``counters`` is the face's: received, lost, unsubscribed,
    malformed, unvouched and the receive budget's (receive_*) are counted there."""

    def __init__(
        self,
        *,
        deliver: Deliver,
        channels: dict[int, ChannelState],
        subscribed: Collection[int],
        counters: dict[str, int],
        status: Callable[[Link], None],
        checking: bool,
        watching: Callable[[], bool] = lambda: False,
    ) -> None:
        """``watching()``: whether the node watches patterns (a Start of a channel it does not
        subscribe to then waits for the ECB's Names, see ``named``)."""
        self._deliver = deliver
        self._watching = watching
        self._channels = channels
        self._subscribed = subscribed
        self._counters = counters
        self.received = 0  #: events delivered (an attribute: counted per event, stats() adds it)
        #: answers a StatusRequest on a link (``status``: ``StatusPacer.ask``) if the identity
        #: may read it (with TLS: those the TCP-ECB names, see ``StatusGate.told``)
        self.gate = StatusGate(status, counters, checking=checking)
        self._checking = checking  # with TLS: events only from vouched-for identities
        self._vouched: dict[int, frozenset[tuple[int, str]]] = {}  # uid -> (node id, identity)
        self._known: set[tuple[int, str]] = set()  # every pair vouched for, on any channel
        self._waiting: set[Link] = set()  # said Hello, not vouched for on any channel yet
        self._links: set[Link] = set()
        self._holding: set[Link] = set()
        self._doorman = Doorman(MAX_PUBLISHERS, counters=counters)  # receive_* counted there
        self._server: asyncio.AbstractServer | None = None
        self._expected: dict[int, dict[int, int]] = {}  # publisher -> uid -> next number
        self._unreported: dict[int, int] = {}  # publisher -> events lost, not logged yet

    async def listen(self, host: str, port: int, tls: ssl.SSLContext | None) -> tuple[str, int]:
        """Open the listening socket; returns the address it is bound to."""
        self._server = await asyncio.get_running_loop().create_server(
            lambda: self._new_link().protocol, host or None, port, reuse_address=True, ssl=tls
        )
        server: Any = self._server  # its sockets: a list on uvloop, a tuple on asyncio
        bound = server.sockets[0].getsockname()
        return bound[0], bound[1]

    def close(self) -> None:
        for link in list(self._links):
            link.close()
        if self._server is not None:
            self._server.close()
        self._doorman.close()

    def vouch(self, uid: int, publishers: tuple[tuple[int, str], ...]) -> None:
        """The ECB says these nodes (node id, identity) publish on ``uid``: admit and release
        links waiting for that.

        What the ECB vouched for once stands while we subscribe (the ACL does not change while
        the ECB runs): a publisher that withdrew still gets its last events through."""
        if not self._wants(uid):
            return
        self._vouched[uid] = self._vouched.get(uid, frozenset()).union(publishers)
        self._known.update(publishers)
        for link in list(self._waiting):
            pub: _Publisher = link.peer
            if (pub.node_id, pub.identity) in self._known:
                self._waiting.discard(link)
                self._doorman.greeted(link)
        for link in list(self._holding):
            self._release(link)

    def _wants(self, uid: int) -> bool:
        """Whether we subscribe to ``uid``: registered, or joined by a pattern just now (its
        Subscribe not sent yet)."""
        state = self._channels.get(uid)
        return uid in self._subscribed or (state is not None and bool(state.subs))

    def named(self) -> None:
        """The ECB named channels to our patterns: links waiting for that go on."""
        for link in list(self._holding):
            if link.peer.awaiting is not None:
                self._release(link)

    def forget(self, uid: int) -> None:
        """We unsubscribed from ``uid``: what comes later is news, and needs the ECB's word."""
        self._vouched.pop(uid, None)
        for link in self._links:
            if link.peer is not None:
                link.peer.allowed.discard(uid)
        for numbers in self._expected.values():
            numbers.pop(uid, None)

    def report(self) -> None:
        """Log the events lost since the last report (called once a second); give back the
        receive buffers that big events grew and that no big event needed since."""
        for link in self._links:
            link.trim()
        for publisher, count in self._unreported.items():
            log.warning("lost %d events from publisher %016x (numbers skipped)", count, publisher)
        self._unreported.clear()

    # --- links -----------------------------------------------------------------------------

    def _new_link(self) -> Link:
        link = Link(self._event, self._frame, self._lost)
        link.keep_big = True  # events of up to 1 MiB may come one after the other
        self._links.add(link)
        self._doorman.admit(link)
        return link

    def _event(self, link: Link, uid: Any, data: bytes, priority: Any, seq: Any) -> None:
        # uid, priority, seq: Any, not int, so that the compiled build keeps them as they came
        # (as ints it would make a new Python int of each for every dict it looks them up in)
        pub: _Publisher | None = link.peer
        if pub is None:
            self._counters["malformed"] += 1
            link.abort("event before Hello")
            return
        if pub.held is not None:  # after one that waits for a voucher: keep the order
            pub.held.append((uid, data, priority, seq))
            return
        state = self._channels.get(uid)
        if state is None or not state.subs:  # we unsubscribed; the publisher will hear of it
            self._counters["unsubscribed"] += 1
            return
        if self._checking and uid not in pub.allowed and not self._allow(pub, uid):
            self._hold(link, (uid, data, priority, seq))
            return
        numbers = pub.expected
        expected = numbers.get(uid)
        if expected is not None and seq > expected:  # numbers skipped: events lost on the way
            self._lost_from(pub.node_id, seq - expected)
        numbers[uid] = seq + 1  # (a lower number: the publisher started again)
        self.received += 1
        self._deliver(state, data, priority, pub.node_id, link.read_at)

    def _frame(self, link: Link, frame: w.Frame) -> None:
        pub: _Publisher | None = link.peer
        if isinstance(frame, w.Hello):
            if pub is None:
                numbers = self._expected.setdefault(frame.node_id, {})
                pub = link.peer = _Publisher(frame.node_id, identity(link.transport), numbers)
                if not self._checking or (pub.node_id, pub.identity) in self._known:
                    self._doorman.greeted(link)
                else:  # full-sized frames, but out at the doorman's timeout unless vouched for
                    self._doorman.lift(link)
                    self._waiting.add(link)
        elif isinstance(frame, w.Start):
            if pub is None:
                self._counters["malformed"] += 1
                link.abort("Start before Hello")
            else:
                self._start(link, pub, frame)
        elif isinstance(frame, w.StatusRequest):
            self._doorman.asked(link)  # evicted last while it waits for its answer
            self.gate.ask(link)
        elif isinstance(frame, w.Ping):
            link.send_control(w.encode(w.Pong()))

    def _start(self, link: Link, pub: _Publisher, frame: w.Start) -> None:
        """Where ``pub``'s events of a channel start; vouched for, and kept in order, as events."""
        if pub.held is not None:
            pub.held.append(frame)
            return
        if self._checking and not self._allow(pub, frame.uid):
            self._hold(link, frame)
            return
        state = self._channels.get(frame.uid)
        if not self._wants(frame.uid):
            if self._watching() and frame.uid not in pub.unnamed:  # its Names may be on the way
                self._hold(link, frame, awaiting=frame.uid)
            return  # else nothing to count for a channel we do not want
        expected = pub.expected.get(frame.uid)
        if expected is not None and frame.seq > expected and state is not None and state.subs:
            self._lost_from(pub.node_id, frame.seq - expected)  # published while we were away
        if expected is None or frame.seq > expected:
            pub.expected[frame.uid] = frame.seq

    def _lost(self, link: Link, reason: str | None) -> None:
        self._links.discard(link)
        self._waiting.discard(link)
        self._doorman.gone(link)
        pub: _Publisher | None = link.peer
        if pub is not None and pub.held is not None:
            self._refuse(link, pub)
        if (
            pub is not None
            and not pub.expected
            and not any(
                other.peer is not None and other.peer.node_id == pub.node_id
                for other in self._links
            )
        ):  # nothing to carry over to the publisher's next link: the table stays bounded
            self._expected.pop(pub.node_id, None)
        if reason is not None and reason.startswith("bad frame"):
            self._counters["malformed"] += 1

    def _lost_from(self, publisher: int, count: int) -> None:
        self._counters["lost"] += count
        self._unreported[publisher] = self._unreported.get(publisher, 0) + count

    # --- vouching --------------------------------------------------------------------------

    def _allow(self, pub: _Publisher, uid: int) -> bool:
        if uid in pub.allowed:
            return True
        if pub.identity is not None and (pub.node_id, pub.identity) in self._vouched.get(uid, ()):
            pub.allowed.add(uid)
            return True
        return False

    def _hold(self, link: Link, first: _HeldEvent | w.Start, awaiting: int | None = None) -> None:
        """Stop reading ``link`` until the ECB vouches for its publisher (or names the channel
        ``awaiting`` to our patterns), or the wait ends."""
        pub: _Publisher = link.peer
        pub.held = [first]
        if pub.timer is not None and pub.awaiting != awaiting:  # waits for something else now
            pub.timer.cancel()
            pub.timer = None
        pub.awaiting = awaiting
        if pub.timer is None:
            loop = asyncio.get_running_loop()
            wait = VOUCH_WAIT if awaiting is None else NAMES_WAIT
            pub.timer = loop.call_later(wait, self._give_up, link)
            link.pause_reading(HELD)
            self._holding.add(link)

    def _release(self, link: Link) -> None:
        """Go on with what ``link`` held, as far as the ECB now vouches for it."""
        pub: _Publisher = link.peer
        held, pub.held = pub.held or [], None
        for i, item in enumerate(held):
            if isinstance(item, w.Start):
                self._start(link, pub, item)
            else:
                self._event(link, *item)
            again = _held(pub)  # (not pub.held: mypyc would keep it None, as mypy narrowed it)
            if again is not None:  # still not vouched for (or named): wait on
                again.extend(held[i + 1 :])
                return
        self._holding.discard(link)
        if pub.timer is not None:
            pub.timer.cancel()
            pub.timer = None
        pub.awaiting = None
        link.resume_reading(HELD)

    def _give_up(self, link: Link) -> None:
        pub: _Publisher = link.peer
        pub.timer = None
        if pub.held is not None and pub.awaiting is not None:  # no name came: go on without
            if len(pub.unnamed) >= _UNNAMED:
                pub.unnamed.clear()
            pub.unnamed.add(pub.awaiting)
            self._release(link)
        elif pub.held is not None:
            self._refuse(link, pub)
            link.abort("events from a publisher the TCP-ECB does not vouch for")

    def _refuse(self, link: Link, pub: _Publisher) -> None:
        held, pub.held = pub.held or [], None
        self._holding.discard(link)
        if pub.timer is not None:
            pub.timer.cancel()
            pub.timer = None
        events = [item for item in held if not isinstance(item, w.Start)]
        if pub.awaiting is not None:  # the link ended while its channel's name was awaited
            self._counters["unsubscribed"] += len(events)
            return
        self._counters["unvouched"] += len(events)
        uids = sorted({f"{item[0]:016x}" for item in events})
        log.warning(
            "refused %d events from %s (node %016x, %s) on %s: the TCP-ECB does not vouch for "
            "it as a publisher",
            len(events), pub.identity, pub.node_id, link.name, ", ".join(uids),
        )  # fmt: skip


def _held(pub: _Publisher) -> list[_HeldEvent | w.Start] | None:
    """What ``pub``'s link holds now (None: it goes on)."""
    return pub.held
