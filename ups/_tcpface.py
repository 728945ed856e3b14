"""The TCP/IP face of a node: registering with the TCP-ECB and delivering straight to peers.

The node keeps one connection to the TCP-ECB, on which it registers its subscriptions and
publications and hears who subscribes to what it publishes. Events never pass through the
ECB: a publisher connects to each subscribing node (at the address that node listens on) and
writes its events there. Those links survive the ECB going away. See docs/protocol.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from . import _tcpwire as w
from ._errors import BrokerUnavailable, ConfigError, UpsError
from ._tcplink import OVERFLOWS, Doorman, Link, Overflow
from ._tls import Tls

if TYPE_CHECKING:
    from ._face import ChannelState, Deliver

log = logging.getLogger("ups.tcp")

DEFAULT_PORT = 7411
HEARTBEAT = 0.5  # seconds between Pings to the ECB
SILENCE = 6 * HEARTBEAT  # an ECB link that said nothing for this long is dead
_RETRY_FIRST = 0.05
_RETRY_MAX = 1.0
_BIND_TIMEOUT = 5.0
_CLOSE_TIMEOUT = 2.0  # at close, how long queued events may take to reach their peers
_EVENT_OVERHEAD = 32  # frame header + msgpack array, kind, uid, bin header, priority, seq
MAX_PUBLISHERS = 1024  #: links from publishers a node accepts at once


def _hex(value: int) -> str:
    return f"0x{value:016x}"


def parse_address(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``HOST:PORT``, ``HOST`` or ``:PORT`` (IPv6 hosts in brackets) -> (host, port)."""
    host, sep, port = text.rpartition(":")
    if not sep or "]" in port:
        host, port = text, str(DEFAULT_PORT)
    host = host.strip("[]") or default_host
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 0xFFFF:
        raise ConfigError(f"expected HOST:PORT, got {text!r}")
    return host, number


class _Peer:
    """A node that subscribes to channels we publish, and our link to it."""

    __slots__ = ("addr", "dropped", "link", "node_id", "reported", "task", "uids")

    def __init__(self, node_id: int, addr: tuple[str, int]) -> None:
        self.node_id = node_id
        self.addr = addr
        self.uids: set[int] = set()
        self.link: Link | None = None
        self.task: asyncio.Task[None] | None = None
        self.dropped = 0  # of links that are gone
        self.reported = 0  # drops already logged

    def total_dropped(self) -> int:
        return self.dropped + (self.link.dropped if self.link else 0)


class TcpFace:
    """A node's face on a TCP/IP network served by one TCP-ECB at ``broker`` (HOST:PORT)."""

    max_payload = w.DEFAULT_MAX_FRAME - _EVENT_OVERHEAD

    def __init__(
        self,
        broker: str,
        node_id: int,
        *,
        name: str,
        deliver: Deliver,
        channels: dict[int, ChannelState],
        node_stats: Callable[[], dict[str, int]],
        listen: str | None,
        join_timeout: float | None,
        peer_queue: int,
        peer_overflow: Overflow,
        tls: Tls | None = None,
    ) -> None:
        if peer_queue < 1:
            raise ConfigError(f"peer_queue must be at least 1, got {peer_queue}")
        if peer_overflow not in OVERFLOWS:
            raise ConfigError(f"peer_overflow must be one of {OVERFLOWS}, got {peer_overflow!r}")
        self.name = name
        self._tls = tls
        self._client_tls = tls.client() if tls else None
        self._deliver = deliver
        self._channels = channels
        self._node_stats = node_stats
        self.broker = parse_address(broker)
        self._listen = parse_address(listen, "") if listen is not None else None
        self.node_id = node_id
        self._join_timeout = join_timeout
        self._peer_queue = peer_queue
        self._peer_overflow: Overflow = peer_overflow
        self.address: tuple[str, int] | None = None  # where we listen, as peers reach us
        self._server: asyncio.AbstractServer | None = None
        self._ecb: Link | None = None
        self._ecb_heard = 0.0
        self._welcome: asyncio.Future[None] | None = None
        self._runner: asyncio.Task[None] | None = None
        self._subscribed: set[int] = set()
        self._advertised: set[int] = set()
        self._acks: dict[int, asyncio.Future[None]] = {}
        self._peers: dict[int, _Peer] = {}
        self._targets: dict[int, list[_Peer]] = {}  # uid -> peers subscribed to it
        self._incoming: set[Link] = set()
        self._doorman = Doorman(MAX_PUBLISHERS)  # links from publishers, bounded
        self._gone_dropped = 0  # events dropped for peers that are no longer subscribers
        self._closing: set[asyncio.Task[None]] = set()  # links to former subscribers
        self._closed = False
        #: called with a UID when its first remote subscriber comes or its last one goes
        self.on_targets: Callable[[int], None] | None = None
        #: more tables for ``ups status`` (the gateway's)
        self.extra_status: Callable[[], dict[str, Any]] | None = None
        self._seq: dict[int, int] = {}  # uid -> number of the last event published
        self._expected: dict[tuple[int, int], int] = {}  # (publisher, uid) -> next number
        self._unreported_lost: dict[int, int] = {}  # publisher -> events lost, not logged yet
        self.counters = dict.fromkeys(
            ("sent", "received", "lost", "unsubscribed", "malformed", "reconnects"), 0
        )

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        deadline = None if self._join_timeout is None else loop.time() + self._join_timeout
        delay = _RETRY_FIRST
        while True:
            try:
                await self._connect_ecb()
                break
            except (OSError, TimeoutError, UpsError) as exc:
                if deadline is not None and loop.time() + delay > deadline:
                    host, port = self.broker
                    raise BrokerUnavailable(
                        f"no TCP-ECB answered at {host}:{port} within {self._join_timeout:g} s "
                        f"({exc}); start one with 'ups broker'"
                    ) from None
                await asyncio.sleep(delay)
                delay = min(delay * 2, _RETRY_MAX)
        self._runner = loop.create_task(self._run())
        log.info(
            "node %016x registered with the TCP-ECB at %s:%d, listening on %s:%d",
            self.node_id,
            *self.broker,
            *self._my_address(),
        )

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._runner is not None:
            self._runner.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._runner
        if self._ecb is not None:
            for uid in self._advertised:
                self._ecb.send_control(w.encode(w.Unadvertise(uid)))
            self._ecb.close()
        peers = list(self._peers.values())
        self._peers.clear()
        self._targets.clear()
        await asyncio.gather(self._close_peers(peers), *self._closing)
        for link in list(self._incoming):
            link.close()
        if self._server is not None:
            self._server.close()
        self._doorman.close()
        for fut in self._acks.values():
            fut.cancel()
        self._report_drops()  # what was lost since the last report

    def stats(self) -> dict[str, int]:
        peers = self._peers.values()
        return {
            **self.counters,
            "peer_dropped": self._gone_dropped + sum(peer.total_dropped() for peer in peers),
            "peers": sum(1 for peer in peers if peer.link and peer.link.transport),
            "queued": sum(peer.link.queued for peer in peers if peer.link),
            "broker_connected": int(self._ecb is not None and not self._ecb.lost.done()),
        }

    def status(self) -> dict[str, Any]:
        """What a StatusRequest on our listening port is answered with."""
        return {
            "node_id": _hex(self.node_id),
            "name": self.name,
            "address": "{}:{}".format(*self._my_address()),
            "stats": self._node_stats(),
            "subscribed": [_hex(uid) for uid in sorted(self._subscribed)],
            "published": [_hex(uid) for uid in sorted(self._advertised)],
            "peers": [
                {
                    "node_id": _hex(peer.node_id),
                    "address": f"{peer.addr[0]}:{peer.addr[1]}",
                    "channels": [_hex(uid) for uid in sorted(peer.uids)],
                    "dropped": peer.total_dropped(),
                    "queued": peer.link.queued if peer.link else 0,
                }
                for peer in self._peers.values()
            ],
            **(self.extra_status() if self.extra_status is not None else {}),
        }

    # --- the Face protocol -----------------------------------------------------------------

    async def bind(self, state: ChannelState, subscribe: bool) -> None:
        uid = state.channel.uid
        registered = self._subscribed if subscribe else self._advertised
        if uid in registered:
            return
        registered.add(uid)
        frame = w.Subscribe(uid) if subscribe else w.Advertise(uid)
        await self._ask(frame, uid)

    async def unsubscribe(self, state: ChannelState) -> None:
        uid = state.channel.uid
        self._subscribed.discard(uid)
        self._to_ecb(w.Unsubscribe(uid))
        for key in [k for k in self._expected if k[1] == uid]:  # what comes later is news
            del self._expected[key]

    def send(self, state: ChannelState, data: bytes, priority: int) -> None:
        uid = state.channel.uid
        seq = self._seq[uid] = self._seq.get(uid, 0) + 1  # numbered even with nobody to hear
        peers = self._targets.get(uid)
        if peers:
            frame = w.encode_event(uid, data, priority, seq)
            for peer in peers:
                assert peer.link is not None
                peer.link.send(frame)
            self.counters["sent"] += len(peers)

    async def room(self, state: ChannelState) -> None:
        """Wait until every subscriber of the channel has room in its queue."""
        for peer in list(self._targets.get(state.channel.uid, ())):
            if peer.link is not None:
                await peer.link.room()

    # --- the ECB link ----------------------------------------------------------------------

    async def _connect_ecb(self) -> None:
        loop = asyncio.get_running_loop()
        self._welcome = loop.create_future()
        host, port = self.broker
        async with asyncio.timeout(_BIND_TIMEOUT):  # not wait_for: 3.11's can swallow a cancel
            _, link = await loop.create_connection(
                self._new_ecb_link, host, port, ssl=self._client_tls
            )
            try:
                if self._server is None:
                    await self._listen_for_peers(link)
                link.send_control(w.encode(w.Hello(self.node_id, self.name, *self._my_address())))
                await self._welcome
            except BaseException:
                link.abort("no welcome")
                raise
        self._ecb = link
        self._ecb_heard = loop.time()
        for uid in self._subscribed:  # after a reconnect: register everything again
            link.send_control(w.encode(w.Subscribe(uid)))
        for uid in self._advertised:
            link.send_control(w.encode(w.Advertise(uid)))
        link.send_control(w.encode(w.Ping()))  # ends the registration: the ECB forgets the rest

    def _new_ecb_link(self) -> Link:
        return Link(self._ecb_event, self._ecb_frame, self._ecb_lost)

    async def _listen_for_peers(self, ecb: Link) -> None:
        assert ecb.transport is not None
        local_host = ecb.transport.get_extra_info("sockname")[0]
        host, port = self._listen or (local_host, 0)
        self._server = await asyncio.get_running_loop().create_server(
            self._new_incoming,
            host or None,
            port,
            reuse_address=True,
            ssl=self._tls.server() if self._tls else None,
        )
        bound = self._server.sockets[0].getsockname()
        self.address = (local_host if host in ("", "0.0.0.0", "::") else bound[0], bound[1])

    def _my_address(self) -> tuple[str, int]:
        assert self.address is not None
        return self.address

    async def _run(self) -> None:
        """Heartbeat the ECB, reconnect when it is gone, and log drops once a second."""
        loop = asyncio.get_running_loop()
        while not self._closed:
            ecb = self._ecb
            if ecb is not None and not ecb.lost.done():
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(asyncio.shield(ecb.lost), HEARTBEAT)
                self._report_drops()
                if not ecb.lost.done():
                    if loop.time() - self._ecb_heard > SILENCE:
                        ecb.abort(f"the TCP-ECB said nothing for {SILENCE:g} s")
                    else:
                        ecb.send_control(w.encode(w.Ping()))
                    continue
            self._ecb = None
            await self._reconnect_ecb()

    async def _reconnect_ecb(self) -> None:
        delay = _RETRY_FIRST
        host, port = self.broker
        log.warning("lost the TCP-ECB at %s:%d; events to known peers keep flowing", host, port)
        while not self._closed:
            await asyncio.sleep(delay)
            self._report_drops()
            try:
                await self._connect_ecb()
            except (OSError, TimeoutError, UpsError) as exc:
                log.debug("TCP-ECB at %s:%d not back yet: %s", host, port, exc)
                delay = min(delay * 2, _RETRY_MAX)
                continue
            self.counters["reconnects"] += 1
            log.info("registered again with the TCP-ECB at %s:%d", host, port)
            return

    def _to_ecb(self, frame: w.Frame) -> None:
        if self._ecb is not None and not self._ecb.lost.done():
            self._ecb.send_control(w.encode(frame))

    async def _ask(self, frame: w.Subscribe | w.Advertise, uid: int) -> None:
        """Register with the ECB and wait for its answer (the channel's subscribers).

        Without an ECB the registration is kept and sent when it is back; meanwhile a publisher
        reaches only the subscribers it already knows.
        """
        if self._ecb is None or self._ecb.lost.done():
            log.warning("no TCP-ECB now: %s registered once it is back", frame)
            return
        fut = self._acks.get(uid)
        if fut is None:
            fut = self._acks[uid] = asyncio.get_running_loop().create_future()
        self._ecb.send_control(w.encode(frame))
        try:
            await asyncio.wait_for(asyncio.shield(fut), _BIND_TIMEOUT)
        except TimeoutError:
            log.warning("the TCP-ECB did not answer %s within %g s", frame, _BIND_TIMEOUT)
        finally:
            if self._acks.get(uid) is fut:
                del self._acks[uid]

    def _ecb_event(self, link: Link, uid: int, data: bytes, priority: int, seq: int) -> None:
        link.abort("the TCP-ECB sent an event")

    def _ecb_frame(self, link: Link, frame: w.Frame) -> None:
        self._ecb_heard = asyncio.get_running_loop().time()
        if isinstance(frame, w.Subscribers):
            self._on_subscribers(frame)
        elif isinstance(frame, w.Hello):
            if self._welcome is not None and not self._welcome.done():
                self._welcome.set_result(None)
        elif isinstance(frame, w.StatusRequest):
            link.send_control(w.encode(w.Status(self.status())))

    def _ecb_lost(self, link: Link, reason: str | None) -> None:
        if reason is not None and self._welcome is not None and not self._welcome.done():
            self._welcome.set_exception(ConnectionError(reason))

    # --- peers we publish to ---------------------------------------------------------------

    def _on_subscribers(self, frame: w.Subscribers) -> None:
        uid = frame.uid
        fut = self._acks.get(uid)
        if fut is not None and not fut.done():
            fut.set_result(None)
        if uid not in self._advertised:
            return
        wanted = {p.node_id: (p.host, p.port) for p in frame.peers if p.node_id != self.node_id}
        targets = []
        for node_id, addr in wanted.items():
            peer = self._peers.get(node_id)
            if peer is not None and peer.addr != addr:  # restarted elsewhere
                self._drop_peer(peer)
                peer = None
            if peer is None:
                peer = self._peers[node_id] = _Peer(node_id, addr)
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
        if had != bool(targets) and self.on_targets is not None:
            self.on_targets(uid)

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
        )
        link.peer = peer
        link.send_control(w.encode(w.Hello(self.node_id, self.name, *self._my_address())))
        delay = 0.0
        if lost is not None:
            link.adopt(lost)
            peer.dropped += lost.dropped
            delay = _RETRY_FIRST
        peer.link = link
        peer.task = asyncio.get_running_loop().create_task(self._dial(peer, link, delay))

    async def _dial(self, peer: _Peer, link: Link, delay: float) -> None:
        loop = asyncio.get_running_loop()
        while not self._closed:
            if delay:
                await asyncio.sleep(delay)
            try:
                async with asyncio.timeout(_BIND_TIMEOUT):
                    await loop.create_connection(lambda: link, *peer.addr, ssl=self._client_tls)
                return
            except (OSError, TimeoutError) as exc:
                delay = min(max(delay * 2, _RETRY_FIRST), _RETRY_MAX)
                log.debug("subscriber %016x at %s:%d: %s", peer.node_id, *peer.addr, exc)

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
            if self._peers.get(peer.node_id) is not peer:  # gone: keep its count
                self._gone_dropped += peer.dropped

    def _report_drops(self) -> None:
        for peer in self._peers.values():
            if peer.total_dropped() > peer.reported:
                self._report(peer)
        for publisher, count in self._unreported_lost.items():
            log.warning("lost %d events from publisher %016x (numbers skipped)", count, publisher)
        self._unreported_lost.clear()

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
        self.counters["malformed"] += 1  # subscribers do not send events back
        link.abort("a subscriber sent an event")

    def _peer_frame(self, link: Link, frame: w.Frame) -> None:
        if isinstance(frame, w.StatusRequest):
            link.send_control(w.encode(w.Status(self.status())))

    # --- publishers that deliver to us -----------------------------------------------------

    def _new_incoming(self) -> Link:
        link = Link(self._incoming_event, self._incoming_frame, self._incoming_lost)
        self._incoming.add(link)
        self._doorman.admit(link)
        return link

    def _incoming_event(self, link: Link, uid: int, data: bytes, priority: int, seq: int) -> None:
        if link.peer is None:
            self.counters["malformed"] += 1
            link.abort("event before Hello")
            return
        state = self._channels.get(uid)
        if state is None or not state.subs:  # we unsubscribed; the publisher will hear of it
            self.counters["unsubscribed"] += 1
            return
        key = (link.peer, uid)
        expected = self._expected.get(key)
        if expected is not None and seq > expected:  # numbers skipped: events lost on the way
            self._lost_from(link.peer, seq - expected)
        self._expected[key] = seq + 1  # (a lower number: the publisher started again)
        self.counters["received"] += 1
        self._deliver(state, data, priority, link.peer, time.time())

    def _lost_from(self, publisher: int, count: int) -> None:
        """Count events of ``publisher`` that never came; logged once a second (_report_drops)."""
        self.counters["lost"] += count
        self._unreported_lost[publisher] = self._unreported_lost.get(publisher, 0) + count

    def _incoming_frame(self, link: Link, frame: w.Frame) -> None:
        if isinstance(frame, w.Hello):
            link.peer = frame.node_id
            self._doorman.greeted(link)
        elif isinstance(frame, w.Start):
            if link.peer is None:
                self.counters["malformed"] += 1
                link.abort("Start before Hello")
                return
            key = (link.peer, frame.uid)
            expected = self._expected.get(key)
            state = self._channels.get(frame.uid)
            if expected is not None and frame.seq > expected and state is not None and state.subs:
                self._lost_from(link.peer, frame.seq - expected)  # published while we were away
            if expected is None or frame.seq > expected:
                self._expected[key] = frame.seq
        elif isinstance(frame, w.StatusRequest):
            link.send_control(w.encode(w.Status(self.status())))
        elif isinstance(frame, w.Ping):
            link.send_control(w.encode(w.Pong()))

    def _incoming_lost(self, link: Link, reason: str | None) -> None:
        self._incoming.discard(link)
        self._doorman.gone(link)
        if reason is not None and reason.startswith("bad frame"):
            self.counters["malformed"] += 1


async def query_status(
    address: str, timeout: float = 5.0, tls: Tls | None = None
) -> dict[str, Any]:
    """Ask the TCP-ECB, gateway or node listening at ``address`` for its tables and counters."""
    host, port = parse_address(address)
    try:
        async with asyncio.timeout(timeout):
            reader, writer = await asyncio.open_connection(
                host, port, ssl=tls.client() if tls else None
            )
            try:
                writer.write(w.encode(w.StatusRequest()))
                decoder = w.Decoder(max_frame=w.MAX_BODY)
                while data := await reader.read(1 << 16):
                    for frame in decoder.feed(data):
                        if isinstance(frame, w.Status):
                            return frame.info
            finally:
                writer.close()
    except (OSError, TimeoutError) as exc:
        raise BrokerUnavailable(f"no status from {host}:{port}: {exc or 'timed out'}") from None
    raise BrokerUnavailable(f"{host}:{port} closed the link without a status")
