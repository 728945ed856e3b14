"""A node's TCP outbox: the links on which it delivers its events to subscribing nodes.

The TCP-ECB tells the node, per channel it publishes on, the channel's subscribers
(``update``). The outbox dials each subscriber once (one link per subscriber, whatever the
channels), numbers the events of each channel (``Start``, then ``seq``) and queues them per
link: a bounded queue whose drops are counted per subscriber. With TLS it writes nothing to a
subscriber whose certificate is not the identity the ECB listed. See docs/protocol.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import ssl
from collections.abc import Callable
from typing import Any

from . import _tcpwire as w
from ._face import Overflow
from ._tcplink import Link
from ._tls import identity

log = logging.getLogger("ups.tcp")

SPLIT = 1 << 14  #: an event with more data than this is queued as (header, data), not joined
#: the longest frame a subscriber may send its publisher (it sends none: a StatusRequest at most)
PEER_FRAME = 4096
_RETRY_FIRST = 0.05
_RETRY_MAX = 1.0
_DIAL_TIMEOUT = 5.0
_CLOSE_TIMEOUT = 2.0  # at close, how long queued events may take to reach their peers


def _hex(value: int) -> str:
    return f"0x{value:016x}"


class _Peer:
    """A node that subscribes to channels we publish, and our link to it."""

    __slots__ = (
        "addr", "dropped", "failures", "identity", "link", "node_id", "reported", "task", "uids",
    )  # fmt: skip

    def __init__(self, node_id: int, addr: tuple[str, int], identity: str | None) -> None:
        self.node_id = node_id
        self.addr = addr
        self.identity = identity  # what its certificate must say (with TLS)
        self.failures = 0  # dials in a row that did not give a usable link
        self.uids: set[int] = set()
        self.link: Link | None = None
        self.task: asyncio.Task[None] | None = None
        self.dropped = 0  # of links that are gone
        self.reported = 0  # drops already logged

    def total_dropped(self) -> int:
        return self.dropped + (self.link.dropped if self.link else 0)


class Outbox:
    """Links to subscribers. ``counters`` is the face's: sent and impostors are counted there;
    ``on_targets(uid)`` is called when a channel's first subscriber comes or its last goes."""

    def __init__(
        self,
        *,
        node_id: int,
        name: str,
        address: Callable[[], tuple[str, int]],
        tls: ssl.SSLContext | None,
        peer_queue: int,
        peer_overflow: Overflow,
        counters: dict[str, int],
        on_targets: Callable[[int], None],
        status: Callable[[Link], None],
    ) -> None:
        self.node_id = node_id
        self.name = name
        self._address = address  # where we listen: our Hello says it
        self._client_tls = tls
        self._peer_queue = peer_queue
        self._peer_overflow: Overflow = peer_overflow
        self._counters = counters
        self.sent = 0  #: event frames queued to subscribers (per event, so not in counters)
        self._on_targets = on_targets
        self._answer_status = status  # answers a subscriber's StatusRequest on a link
        self._peers: dict[int, _Peer] = {}
        self._targets: dict[int, list[_Peer]] = {}  # uid -> peers subscribed to it
        self._seq: dict[int, int] = {}  # uid -> number of the last event published
        self._gone_dropped = 0  # events dropped for peers that are no longer subscribers
        self._leaving: list[_Peer] = []  # former subscribers whose links are closing
        self._closing: set[asyncio.Task[None]] = set()  # links to former subscribers
        self._closed = False

    def send(self, uid: int, data: bytes, priority: int) -> None:
        seq = self._seq[uid] = self._seq.get(uid, 0) + 1  # numbered even with nobody to hear
        peers = self._targets.get(uid)
        if peers:
            frame: bytes | tuple[bytes, bytes]
            if len(data) > SPLIT:  # written after its header as it is: never copied here
                frame = (w.event_header(uid, len(data), priority, seq), data)
            else:
                frame = w.encode_event(uid, data, priority, seq)
            for peer in peers:
                assert peer.link is not None
                peer.link.send(frame)
            self.sent += len(peers)

    async def room(self, uid: int) -> None:
        """Wait until every subscriber of the channel has room in its queue."""
        peers = self._targets.get(uid, ())
        for peer in peers:  # the common case: all have room, and nothing is awaited
            if peer.link is not None and peer.link.full:
                break
        else:
            return
        for peer in list(peers):
            if peer.link is not None:
                await peer.link.room()

    async def close(self) -> None:
        """Give queued events up to 2 s to go out, then close every link (the rest is counted)."""
        self._closed = True
        peers = list(self._peers.values())
        self._peers.clear()
        self._targets.clear()
        await asyncio.gather(self._close_peers(peers), *self._closing)

    def stats(self) -> dict[str, int]:
        peers = self._peers.values()
        return {
            "peer_dropped": self._gone_dropped
            + sum(peer.total_dropped() for peer in peers)
            + sum(peer.total_dropped() for peer in self._leaving),
            "peers": sum(1 for peer in peers if peer.link and peer.link.transport),
            "queued": sum(peer.link.queued for peer in peers if peer.link),
        }

    def status(self) -> list[dict[str, Any]]:
        return [
            {
                "node_id": _hex(peer.node_id),
                "address": f"{peer.addr[0]}:{peer.addr[1]}",
                "channels": [_hex(uid) for uid in sorted(peer.uids)],
                "dropped": peer.total_dropped(),
                "queued": peer.link.queued if peer.link else 0,
            }
            for peer in self._peers.values()
        ]

    def update(self, frame: w.Subscribers) -> None:
        """The ECB's current subscriber list of a channel we publish on: dial the new ones,
        let go of those that left."""
        uid = frame.uid
        wanted = {p.node_id: p for p in frame.peers if p.node_id != self.node_id}
        targets = []
        for node_id, listed in wanted.items():
            addr = (listed.host, listed.port)
            peer = self._peers.get(node_id)
            if peer is not None and (peer.addr, peer.identity) != (addr, listed.identity):
                self._drop_peer(peer)  # restarted elsewhere
                peer = None
            if peer is None:
                peer = self._peers[node_id] = _Peer(node_id, addr, listed.identity)
                self._connect_peer(peer)
            if uid not in peer.uids:  # its events of uid start with the next one published
                peer.uids.add(uid)
                assert peer.link is not None
                peer.link.send_control(w.encode(w.Start(uid, self._seq.get(uid, 0) + 1)))
            targets.append(peer)
        for peer in self._targets.get(uid, ()):
            if peer.node_id not in wanted:
                peer.uids.discard(uid)
                if not peer.uids:
                    self._drop_peer(peer)
        had = uid in self._targets
        if targets:
            self._targets[uid] = targets
        else:
            self._targets.pop(uid, None)
        if had != bool(targets):
            self._on_targets(uid)

    def subscribed_elsewhere(self, uid: int) -> bool:
        """Whether another node subscribes to ``uid`` (known for channels we publish on)."""
        return uid in self._targets

    def _connect_peer(self, peer: _Peer, lost: Link | None = None) -> None:
        """Dial ``peer``; when ``lost`` is its old link, what that had not written goes first."""
        link = Link(
            self._peer_event,
            self._peer_frame,
            self._peer_lost,
            limit=self._peer_queue,
            overflow=self._peer_overflow,
            max_frame=PEER_FRAME,  # so its receive buffer never grows
        )
        link.peer = peer
        link.verify = functools.partial(self._verify, peer)
        link.send_control(w.encode(w.Hello(self.node_id, self.name, *self._address())))
        delay = 0.0
        if lost is not None:
            link.adopt(lost)
            peer.dropped += lost.dropped
            delay = min(_RETRY_FIRST * 2**peer.failures, _RETRY_MAX)
        peer.link = link
        peer.task = asyncio.get_running_loop().create_task(self._dial(peer, link, delay))

    async def _dial(self, peer: _Peer, link: Link, delay: float) -> None:
        loop = asyncio.get_running_loop()
        while not self._closed:
            if delay:
                await asyncio.sleep(delay)
            try:
                async with asyncio.timeout(_DIAL_TIMEOUT):
                    await loop.create_connection(
                        lambda: link.protocol, *peer.addr, ssl=self._client_tls
                    )
            except (OSError, TimeoutError) as exc:
                delay = min(max(delay * 2, _RETRY_FIRST), _RETRY_MAX)
                log.debug("subscriber %016x at %s:%d: %s", peer.node_id, *peer.addr, exc)
                continue
            return

    def _verify(self, peer: _Peer, transport: asyncio.BaseTransport) -> str | None:
        """With TLS, a subscriber must show the identity the ECB listed it with: else nothing
        queued for it is written, and the link is closed."""
        shown = identity(transport)
        if self._client_tls is None or shown == peer.identity:
            peer.failures = 0
            return None
        self._counters["impostors"] += 1
        peer.failures += 1
        log.warning("subscriber %016x at %s:%d shows identity %r, not %r: closed",
                    peer.node_id, *peer.addr, shown, peer.identity)  # fmt: skip
        return f"identity {shown!r} is not the subscriber's"

    def _peer_lost(self, link: Link, reason: str | None) -> None:
        peer: _Peer = link.peer
        if reason is None or peer.link is not link or self._peers.get(peer.node_id) is not peer:
            return  # closed by us, replaced, or no longer a subscriber
        log.info("link to subscriber %016x lost (%s); dialling again", peer.node_id, reason)
        self._connect_peer(peer, lost=link)

    def _drop_peer(self, peer: _Peer) -> None:
        """``peer`` subscribes to nothing we publish any more: close its link."""
        self._peers.pop(peer.node_id, None)
        for uid in peer.uids:
            targets = self._targets.get(uid)
            if targets and peer in targets:
                targets.remove(peer)
        peer.uids.clear()
        task = asyncio.get_running_loop().create_task(self._close_peers([peer]))
        self._closing.add(task)
        task.add_done_callback(self._closing.discard)

    async def _close_peers(self, peers: list[_Peer]) -> None:
        """Give each peer's queued events a moment to go out, then close its link; what is
        still queued after that is dropped, and counted."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + _CLOSE_TIMEOUT
        # Former subscribers (no longer in _peers) are counted from _leaving while their links
        # close, which takes up to _CLOSE_TIMEOUT; then from _gone_dropped.
        self._leaving += [p for p in peers if p.link and self._peers.get(p.node_id) is not p]
        for peer in peers:
            link, task = peer.link, peer.task
            if link is None:
                continue
            if task is not None and not task.done() and link.queued:
                with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                    await asyncio.wait_for(asyncio.shield(task), max(0.0, deadline - loop.time()))
            if task is not None:
                task.cancel()
            link.close()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(link.lost), max(0.0, deadline - loop.time()))
            unsent = link.queued
            if not link.lost.done():
                link.abort("closing")
            peer.dropped += link.dropped + unsent
            peer.link = None
            if peer.dropped > peer.reported:
                self._report(peer)
            if peer in self._leaving:  # gone: keep its count
                self._leaving.remove(peer)
                self._gone_dropped += peer.dropped

    def report(self) -> None:
        """Log the drops since the last report (called once a second)."""
        for peer in self._peers.values():
            if peer.total_dropped() > peer.reported:
                self._report(peer)

    def _report(self, peer: _Peer) -> None:
        total = peer.total_dropped()
        log.warning(
            "dropped %d events for subscriber %016x at %s:%d (%d in all): it does not read "
            "them, and its queue of %d is full (%s) or was left at close",
            total - peer.reported,
            peer.node_id,
            *peer.addr,
            total,
            self._peer_queue,
            self._peer_overflow,
        )
        peer.reported = total

    def _peer_event(self, link: Link, uid: int, data: bytes, priority: int, seq: int) -> None:
        self._counters["malformed"] += 1  # subscribers do not send events back
        link.abort("a subscriber sent an event")

    def _peer_frame(self, link: Link, frame: w.Frame) -> None:
        if isinstance(frame, w.StatusRequest):
            self._answer_status(link)
