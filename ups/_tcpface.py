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
import re
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from . import _tcpwire as w
from ._address import parse_address
from ._errors import (
    AccessDenied,
    BrokerUnavailable,
    ConfigError,
    PayloadTooLarge,
    UpsError,
)
from ._face import OVERFLOWS, Found, Overflow
from ._statuspacer import StatusPacer
from ._subscription import DEFAULT_QUEUE
from ._tcpinbox import Inbox
from ._tcplink import Link
from ._tcpoutbox import Outbox
from ._tcpquery import query_status as query_status
from ._tcpwatch import TcpWatches  # it lived here: importers keep working
from ._tls import Tls, identity
from ._tlsprobe import mismatch

if TYPE_CHECKING:
    from ._face import ChannelState, Deliver, FaceContext

log = logging.getLogger("ups.tcp")

HEARTBEAT = 0.5  # seconds between Pings to the ECB
SILENCE = 6 * HEARTBEAT  # an ECB link that said nothing for this long is dead
_RETRY_FIRST = 0.05
_RETRY_MAX = 1.0
_BIND_TIMEOUT = 5.0


#: the Node options a TCP/IP face takes (see ``Node``)
OPTIONS = frozenset({"listen", "peer_queue", "peer_overflow", "tls"})


def build(
    broker: str,
    context: FaceContext,
    *,
    listen: str | None = None,
    peer_queue: int = DEFAULT_QUEUE,
    peer_overflow: Overflow = "drop_oldest",
    tls: Tls | None = None,
) -> TcpFace:
    return TcpFace(
        broker,
        context.node_id,
        name=context.name,
        deliver=context.deliver,
        channels=context.channels,
        node_stats=context.node_stats,
        listen=listen,
        join_timeout=context.join_timeout,
        peer_queue=peer_queue,
        peer_overflow=peer_overflow,
        tls=tls,
    )


def _hex(value: int) -> str:
    return f"0x{value:016x}"


class TcpFace:
    """A node's face on a TCP/IP network served by one TCP-ECB at ``broker`` (HOST:PORT)."""

    max_payload = w.MAX_DATA

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
        self.where = f"the TCP-ECB at {broker}"
        self._listen = parse_address(listen, "") if listen is not None else None
        self.node_id = node_id
        self._join_timeout = join_timeout
        self.address: tuple[str, int] | None = None  # where we listen, as peers reach us
        self._server: asyncio.AbstractServer | None = None
        self._ecb: Link | None = None
        self._ecb_heard = 0.0
        self._welcome: asyncio.Future[None] | None = None
        self._runner: asyncio.Task[None] | None = None
        self._subscribed: set[int] = set()
        self._advertised: set[int] = set()
        self._acks: dict[tuple[bool, int], asyncio.Future[None]] = {}  # (subscribe, uid)
        self._closed = False
        #: called with a UID when its first remote subscriber comes or its last one goes
        self.on_targets: Callable[[int], None] | None = None
        #: more tables for ``ups status`` (the gateway's)
        self.extra_status: Callable[[], dict[str, Any]] | None = None
        self.counters = dict.fromkeys(
            ("lost", "unsubscribed", "malformed", "reconnects", "denied", "unvouched",
             "impostors"), 0,
        )  # fmt: skip
        self._watches = TcpWatches(self.counters, _BIND_TIMEOUT)  # patterns: see _tcpwatch
        #: answers every StatusRequest (listening port, links to subscribers, the ECB link)
        self._pacer = StatusPacer(self.status, self.counters, who=f"node {node_id:016x}")
        self._inbox = Inbox(
            deliver=deliver,
            channels=channels,
            subscribed=self._subscribed,
            watching=lambda: self._watches.active,
            counters=self.counters,
            status=self._pacer.ask,
            checking=tls is not None,
        )
        self._outbox = Outbox(
            node_id=node_id,
            name=name,
            address=self._my_address,
            tls=self._client_tls,
            peer_queue=peer_queue,
            peer_overflow=peer_overflow,
            counters=self.counters,
            on_targets=self._targets_changed,
            status=self._inbox.gate.ask,  # the status right, as on our listening port
        )

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        deadline = None if self._join_timeout is None else loop.time() + self._join_timeout
        delay = _RETRY_FIRST
        probed = False  # whether TLS on one side only was looked for (once)
        while True:
            try:
                await self._connect_ecb()
                break
            except AccessDenied:
                raise
            except (OSError, TimeoutError, UpsError) as exc:
                if not probed and not isinstance(exc, ConnectionRefusedError | TimeoutError):
                    probed = True  # it answered, and hung up: it may speak TLS, or not
                    why = await mismatch(*self.broker, self._tls, "the TCP-ECB")
                    if why is not None:
                        raise ConfigError(why) from None
                if deadline is not None and loop.time() + delay > deadline:
                    raise BrokerUnavailable(self._unavailable(exc)) from None
                await asyncio.sleep(delay)
                delay = min(delay * 2, _RETRY_MAX)
        self._runner = loop.create_task(self._run())
        log.info(
            "node %016x registered with the TCP-ECB at %s:%d, listening on %s:%d",
            self.node_id,
            *self.broker,
            *self._my_address(),
        )

    def _unavailable(self, exc: BaseException) -> str:
        """Why joining failed, for people: nothing listening, or no answer."""
        host, port = self.broker
        waited = f" within {self._join_timeout:g} s" if self._join_timeout else ""
        if isinstance(exc, ConnectionRefusedError):
            listens = "listened" if waited else "listens"
            return (
                f"nothing {listens} at {host}:{port}{waited} (connection refused); start a "
                f"TCP-ECB there with 'ups broker --listen {host}:{port}'"
            )
        reason = re.sub(r"^\[Errno -?\d+\] ", "", str(exc)) or "no answer"
        return f"no TCP-ECB answered at {host}:{port}{waited} ({reason})"

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
            for frame in self._watches.frames(w.Unwatch):  # its pattern subscriptions too
                self._ecb.send_control(frame)
            self._ecb.close()
        await self._outbox.close()
        self._inbox.close()
        self._pacer.close()
        for fut in self._acks.values():
            fut.cancel()
        self._watches.close()
        self._report_drops()  # what was lost since the last report

    def stats(self) -> dict[str, int]:
        return {
            "sent": self._outbox.sent,
            "received": self._inbox.received,
            **self.counters,
            **self._outbox.stats(),
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
            "peers": self._outbox.status(),
            **(self.extra_status() if self.extra_status is not None else {}),
        }

    # --- the Face protocol -----------------------------------------------------------------

    async def bind(self, state: ChannelState, subscribe: bool, size: int = 0) -> None:
        state.max_size = self.max_payload
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

    async def grow(self, state: ChannelState, size: int) -> None:
        """Every channel carries the largest event a frame holds: no more."""
        raise PayloadTooLarge(
            f"{size} bytes do not fit one event on {state.channel} (at most {self.max_payload})"
        )

    async def unsubscribe(self, state: ChannelState) -> None:
        uid = state.channel.uid
        self._subscribed.discard(uid)
        self._to_ecb(w.Unsubscribe(uid))
        self._inbox.forget(uid)

    def send(self, state: ChannelState, data: bytes, priority: int) -> None:
        self._outbox.send(state.channel.uid, data, priority)

    async def room(self, state: ChannelState) -> None:
        """Wait until every subscriber of the channel has room in its queue."""
        await self._outbox.room(state.channel.uid)

    async def watch(self, pattern: str, found: Found) -> None:
        """The TCP-ECB names the channels it knows that match (Watch, Names)."""
        ecb = self._ecb if self._ecb is not None and not self._ecb.lost.done() else None
        await self._watches.watch(pattern, found, None if ecb is None else ecb.send_control)

    async def unwatch(self, pattern: str) -> None:
        frame = self._watches.unwatch(pattern)
        if frame is not None and self._ecb is not None and not self._ecb.lost.done():
            self._ecb.send_control(frame)

    # --- the ECB link ----------------------------------------------------------------------

    async def _connect_ecb(self) -> None:
        loop = asyncio.get_running_loop()
        self._welcome = loop.create_future()
        host, port = self.broker
        async with asyncio.timeout(_BIND_TIMEOUT):  # not wait_for: 3.11's can swallow a cancel
            link = self._new_ecb_link()
            await loop.create_connection(lambda: link.protocol, host, port, ssl=self._client_tls)
            try:
                if link.lost.done():  # refused at once: not the broker (see _verify_ecb)
                    await self._welcome  # raises why
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
        for frame in self._watches.frames():
            link.send_control(frame)
        link.send_control(w.encode(w.Ping()))  # ends the registration: the ECB forgets the rest

    def _new_ecb_link(self) -> Link:
        link = Link(self._ecb_event, self._ecb_frame, self._ecb_lost)
        link.verify = self._verify_ecb
        return link

    def _verify_ecb(self, transport: asyncio.BaseTransport) -> str | None:
        """With TLS, the TCP-ECB must show the fleet broker's identity: a node that joined
        another participant posing as the ECB would let it decide who hears what."""
        if self._tls is None:
            return None
        shown = identity(transport)
        if shown == self._tls.broker:
            return None
        return f"the TCP-ECB shows identity {shown!r}, not the broker's ({self._tls.broker!r})"

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
            self._inbox.vouch(frame.uid, frame.publishers)
            self._acked(True, frame.uid)
        elif isinstance(frame, w.Refused):
            self._on_refused(frame)
        elif isinstance(frame, w.Names):
            self._watches.names(frame)
            self._inbox.named()  # a publisher's Start may have come before the names
        elif isinstance(frame, w.Hello):
            if self._welcome is not None and not self._welcome.done():
                self._welcome.set_result(None)
        elif isinstance(frame, w.StatusRequest):
            self._pacer.ask(link)
        elif isinstance(frame, w.StatusReaders):  # who may read our Status on our own links
            self._inbox.gate.told(frame.identities)

    def _on_refused(self, frame: w.Refused) -> None:
        self.counters["denied"] += 1
        state = self._channels.get(frame.uid)
        channel = str(state.channel) if state is not None else _hex(frame.uid)
        if frame.right == "connect":
            error = AccessDenied(f"the TCP-ECB refused this node: {frame.reason}", "", "connect")
            if self._welcome is not None and not self._welcome.done():
                self._welcome.set_exception(error)
            return
        if frame.right == "watch":
            self._watches.refused(frame)
        if frame.right not in ("publish", "subscribe"):
            return
        subscribe = frame.right == "subscribe"
        error = AccessDenied(
            f"the TCP-ECB does not let this node {frame.right} {channel}: {frame.reason}",
            channel,
            frame.right,
        )
        (self._subscribed if subscribe else self._advertised).discard(frame.uid)
        if not subscribe:  # no longer a publisher of it: its subscribers get nothing more
            self._outbox.update(w.Subscribers(frame.uid, ()))
        if (subscribe, frame.uid) in self._acks:
            self._acked(subscribe, frame.uid, error)
        else:  # a registration renewed after a reconnect
            log.error("%s", error)

    def _ecb_lost(self, link: Link, reason: str | None) -> None:
        if reason is not None and self._welcome is not None and not self._welcome.done():
            self._welcome.set_exception(ConnectionError(reason))

    # --- peers we publish to ---------------------------------------------------------------

    def _on_subscribers(self, frame: w.Subscribers) -> None:
        self._acked(False, frame.uid)
        if frame.uid in self._advertised:
            self._outbox.update(frame)

    def subscribed_elsewhere(self, uid: int) -> bool:
        """Whether another node subscribes to ``uid`` (known for channels we publish on)."""
        return self._outbox.subscribed_elsewhere(uid)

    def _targets_changed(self, uid: int) -> None:
        if self.on_targets is not None:
            self.on_targets(uid)

    def _report_drops(self) -> None:
        self._outbox.report()
        self._inbox.report()
