"""The TCP/IP face of a node: registering with the TCP-ECB and delivering straight to peers.

The node keeps one connection to the TCP-ECB, on which it registers its subscriptions and
publications and hears who subscribes to what it publishes. Events never pass through the
ECB: a publisher connects to each subscribing node (at the address that node listens on) and
writes its events there. Those links survive the ECB going away. See docs/protocol.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from . import _tcpwire as w
from ._errors import AccessDenied, BrokerUnavailable, ConfigError, UpsError
from ._tcpinbox import Inbox
from ._tcplink import OVERFLOWS, Link, Overflow
from ._tls import Tls, identity

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
        self._acks: dict[tuple[bool, int], asyncio.Future[None]] = {}  # (subscribe, uid)
        self._peers: dict[int, _Peer] = {}
        self._targets: dict[int, list[_Peer]] = {}  # uid -> peers subscribed to it
        self._gone_dropped = 0  # events dropped for peers that are no longer subscribers
        self._closing: set[asyncio.Task[None]] = set()  # links to former subscribers
        self._closed = False
        #: called with a UID when its first remote subscriber comes or its last one goes
        self.on_targets: Callable[[int], None] | None = None
        #: more tables for ``ups status`` (the gateway's)
        self.extra_status: Callable[[], dict[str, Any]] | None = None
        self._seq: dict[int, int] = {}  # uid -> number of the last event published
        self.counters = dict.fromkeys(
            ("sent", "received", "lost", "unsubscribed", "malformed", "reconnects", "denied",
             "unvouched", "impostors"), 0,
        )  # fmt: skip
        self._inbox = Inbox(
            deliver=deliver,
            channels=channels,
            subscribed=self._subscribed,
            counters=self.counters,
            status=self.status,
            checking=tls is not None,
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
            except AccessDenied:
                raise
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
        self._inbox.close()
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
        try:
            await self._ask(self._registration(uid, subscribe), subscribe, uid)
        except AccessDenied:
            registered.discard(uid)
            raise

    def _registration(self, uid: int, subscribe: bool) -> w.Subscribe | w.Advertise:
        """Subscribe or Advertise, with the channel's name when we know it."""
        state = self._channels.get(uid)
        name = state.channel.name if state is not None else None
        return w.Subscribe(uid, name) if subscribe else w.Advertise(uid, name)

    async def unsubscribe(self, state: ChannelState) -> None:
        uid = state.channel.uid
        self._subscribed.discard(uid)
        self._to_ecb(w.Unsubscribe(uid))
        self._inbox.forget(uid)

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
                if self.address is None:
                    await self._listen_for_peers(link)
                link.send_control(w.encode(w.Hello(self.node_id, self.name, *self._my_address())))
                await self._welcome
            except BaseException:
                link.abort("no welcome")
                raise
        self._ecb = link
        self._ecb_heard = loop.time()
        for uid in self._subscribed:  # after a reconnect: register everything again
            link.send_control(w.encode(self._registration(uid, True)))
        for uid in self._advertised:
            link.send_control(w.encode(self._registration(uid, False)))
        link.send_control(w.encode(w.Ping()))  # ends the registration: the ECB forgets the rest

    def _new_ecb_link(self) -> Link:
        return Link(self._ecb_event, self._ecb_frame, self._ecb_lost)

    async def _listen_for_peers(self, ecb: Link) -> None:
        assert ecb.transport is not None
        local_host = ecb.transport.get_extra_info("sockname")[0]
        host, port = self._listen or (local_host, 0)
        tls = self._tls.server() if self._tls else None
        bound = await self._inbox.listen(host, port, tls)
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
                level = logging.WARNING if isinstance(exc, AccessDenied) else logging.DEBUG
                log.log(level, "TCP-ECB at %s:%d not back yet: %s", host, port, exc)
                delay = min(delay * 2, _RETRY_MAX)
                continue
            self.counters["reconnects"] += 1
            log.info("registered again with the TCP-ECB at %s:%d", host, port)
            return

    def _to_ecb(self, frame: w.Frame) -> None:
        if self._ecb is not None and not self._ecb.lost.done():
            self._ecb.send_control(w.encode(frame))

    async def _ask(self, frame: w.Subscribe | w.Advertise, subscribe: bool, uid: int) -> None:
        """Register with the ECB and wait for its answer (the channel's subscribers).

        Without an ECB the registration is kept and sent when it is back; meanwhile a publisher
        reaches only the subscribers it already knows.
        """
        if self._ecb is None or self._ecb.lost.done():
            log.warning("no TCP-ECB now: %s registered once it is back", frame)
            return
        key = (subscribe, uid)
        fut = self._acks.get(key)
        if fut is None:
            fut = self._acks[key] = asyncio.get_running_loop().create_future()
        self._ecb.send_control(w.encode(frame))
        try:
            await asyncio.wait_for(asyncio.shield(fut), _BIND_TIMEOUT)
        except TimeoutError:
            log.warning("the TCP-ECB did not answer %s within %g s", frame, _BIND_TIMEOUT)
        finally:
            if self._acks.get(key) is fut:
                del self._acks[key]

    def _acked(self, subscribe: bool, uid: int, error: AccessDenied | None = None) -> None:
        fut = self._acks.get((subscribe, uid))
        if fut is not None and not fut.done():
            if error is None:
                fut.set_result(None)
            else:
                fut.set_exception(error)
                fut.exception()  # retrieved: the waiter may have timed out already

    def _ecb_event(self, link: Link, uid: int, data: bytes, priority: int, seq: int) -> None:
        link.abort("the TCP-ECB sent an event")

    def _ecb_frame(self, link: Link, frame: w.Frame) -> None:
        self._ecb_heard = asyncio.get_running_loop().time()
        if isinstance(frame, w.Subscribers):
            self._on_subscribers(frame)
        elif isinstance(frame, w.Publishers):
            self._inbox.vouch(frame.uid, frame.identities)
            self._acked(True, frame.uid)
        elif isinstance(frame, w.Refused):
            self._on_refused(frame)
        elif isinstance(frame, w.Hello):
            if self._welcome is not None and not self._welcome.done():
                self._welcome.set_result(None)
        elif isinstance(frame, w.StatusRequest):
            link.send_control(w.encode(w.Status(self.status())))

    def _on_refused(self, frame: w.Refused) -> None:
        self.counters["denied"] += 1
        state = self._channels.get(frame.uid)
        channel = str(state.channel) if state is not None else _hex(frame.uid)
        if frame.right == "connect":
            error = AccessDenied(f"the TCP-ECB refused this node: {frame.reason}", "", "connect")
            if self._welcome is not None and not self._welcome.done():
                self._welcome.set_exception(error)
            return
        if frame.right not in ("publish", "subscribe"):
            return
        subscribe = frame.right == "subscribe"
        error = AccessDenied(
            f"the TCP-ECB does not let this node {frame.right} {channel}: {frame.reason}",
            channel,
            frame.right,
        )
        (self._subscribed if subscribe else self._advertised).discard(frame.uid)
        if (subscribe, frame.uid) in self._acks:
            self._acked(subscribe, frame.uid, error)
        else:  # a registration renewed after a reconnect
            log.error("%s", error)

    def _ecb_lost(self, link: Link, reason: str | None) -> None:
        if reason is not None and self._welcome is not None and not self._welcome.done():
            self._welcome.set_exception(ConnectionError(reason))

    # --- peers we publish to ---------------------------------------------------------------

    def _on_subscribers(self, frame: w.Subscribers) -> None:
        uid = frame.uid
        self._acked(False, uid)
        if uid not in self._advertised:
            return
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
        link.verify = functools.partial(self._verify, peer)
        link.send_control(w.encode(w.Hello(self.node_id, self.name, *self._my_address())))
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
                async with asyncio.timeout(_BIND_TIMEOUT):
                    await loop.create_connection(lambda: link, *peer.addr, ssl=self._client_tls)
            except (OSError, TimeoutError) as exc:
                delay = min(max(delay * 2, _RETRY_FIRST), _RETRY_MAX)
                log.debug("subscriber %016x at %s:%d: %s", peer.node_id, *peer.addr, exc)
                continue
            return

    def _verify(self, peer: _Peer, transport: asyncio.BaseTransport) -> str | None:
        """With TLS, a subscriber must show the identity the ECB listed it with: else nothing
        queued for it is written, and the link is closed."""
        shown = identity(transport)
        if self._tls is None or shown == peer.identity:
            peer.failures = 0
            return None
        self.counters["impostors"] += 1
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
        self._inbox.report()

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
                        if isinstance(frame, w.Refused):
                            raise AccessDenied(
                                f"{host}:{port} does not show its status: {frame.reason}",
                                "",
                                frame.right,
                            )
            finally:
                writer.close()
    except (OSError, TimeoutError) as exc:
        raise BrokerUnavailable(f"no status from {host}:{port}: {exc or 'timed out'}") from None
    raise BrokerUnavailable(f"{host}:{port} closed the link without a status")
