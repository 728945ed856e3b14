"""The Event Channel Handler (ECH): the node object applications use.

A node keeps a table of the channels its applications use, delivers each event to the local
subscriptions of its channel, and hands publications to its *face*: the part that talks to one
network (CAN or TCP/IP). Faces implement the small ``Face`` protocol below; everything network
specific lives there.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, Final

from ._channel import Channel, ChannelLike, as_channel, as_literal, check_pattern, is_pattern
from ._errors import Closed, ConfigError
from ._face import DEFAULT_PRIORITY, OVERFLOWS, ChannelState, Face, FaceContext, Overflow, Sink
from ._message import Message
from ._network import build_face, choose
from ._nodeid import claim_node_id
from ._patterns import Watching
from ._subscription import DEFAULT_QUEUE, YIELD_EVERY, Subscription, wait
from ._tls import Tls

log = logging.getLogger("ups")

_new_message: Final = tuple.__new__  # Message(...) without NamedTuple's Python-level __new__


class Node:
    """An Event Channel Handler on one network: a CAN bus, a TCP/IP network with a TCP-ECB, or
    a Zenoh network.

    Use it as an async context manager; the API is the same on every network::

        async with Node(can="virtual:demo") as node:  # or broker="127.0.0.1:7411", or
            # zenoh="tcp/127.0.0.1:7447"
            sub = await node.subscribe("robot/speed")
            await node.publish("robot/speed", b"\\x10")
            msg = await sub.get_msg(timeout=1.0)

    ``node_id`` is the node's 64-bit identity (its TxNode on CAN is keyed by it); by default it
    is derived from this machine, ``name`` and a per-machine slot, so it is stable across
    restarts and distinct between copies running at once. ``join_timeout`` bounds the wait for
    the network's broker (None: wait forever, retrying).

    CAN only: ``filter_limit``: a node subscribed to at most this many channels installs one
    acceptance filter per etag (in the kernel on SocketCAN); beyond it, it receives every frame
    and filters in software. ``max_event``: the largest event (in bytes) this node buffers; it
    refuses (``PayloadTooLarge``) to subscribe to a channel whose size class carries larger ones.
    Events up to 65535 bytes travel as transfers of several frames (CAN FD frames on a bus
    opened with ``fd=True``). ``catalog``: a channel catalog (a file, see ``docs/files.md``):
    on CAN, where frames carry no names, the channels a pattern subscription may match.

    TCP/IP only: ``listen`` (HOST:PORT) is where publishers reach this node; by default the
    address it reaches the TCP-ECB from, on a free port. Each subscribing peer gets a queue of
    ``peer_queue`` events that the peer has not read yet; when it is full, ``peer_overflow``
    (``"drop_oldest"`` or ``"drop_newest"``) decides what is dropped, and
    ``stats()["peer_dropped"]`` counts it: a stalled subscriber never holds up the publisher
    or the other subscribers. ``tls`` (``ups.Tls(ca, cert, key)``) runs every link over TLS
    with the fleet's certificates, both sides authenticated.

    Zenoh only: ``zenoh`` is the endpoint of a Zenoh router to join as a client (e.g.
    ``tcp/10.0.0.1:7447``); ``zenoh_config``, a Zenoh JSON5 config file (TLS, user/password,
    access control, scouting), alone or beside it. Needs ``pip install 'ups-pubsub[zenoh]'``.

    An option of another network than the node's (``listen`` on a CAN node, say) is a
    ``ConfigError``.
    """

    def __init__(
        self,
        *,
        can: Any = None,
        broker: str | None = None,
        zenoh: str | None = None,
        node_id: int | None = None,
        name: str | None = None,
        join_timeout: float | None = 30.0,
        filter_limit: int | None = None,
        max_event: int | None = None,
        listen: str | None = None,
        peer_queue: int | None = None,
        peer_overflow: Overflow | None = None,
        tls: Tls | None = None,
        zenoh_config: str | Path | None = None,
        catalog: str | Path | None = None,
    ) -> None:
        self._network, self._where = choose(can, broker, zenoh, zenoh_config)
        if node_id is not None and not 0 <= node_id < 1 << 64:
            raise ConfigError(f"node_id must fit in 64 bits, got {node_id!r}")
        options: dict[str, Any] = dict(
            filter_limit=filter_limit, max_event=max_event, listen=listen, peer_queue=peer_queue,
            peer_overflow=peer_overflow, tls=tls, config=zenoh_config, catalog=catalog,
        )  # fmt: skip
        # the options of one kind of network: its face refuses those that are not its own
        self._options = {key: value for key, value in options.items() if value is not None}
        self.name = name or _program_name()
        self._node_id = node_id
        self._id_lock: IO[bytes] | None = None
        self._join_timeout = join_timeout
        self._tls = tls
        self._face: Face | None = None
        self._states: dict[int, ChannelState] = {}
        self._publishing: dict[ChannelLike, ChannelState] = {}
        self._priorities: dict[int, int] = {}
        self._subs: list[Subscription] = []
        self._watching = Watching(self._state, lambda: self.face)
        self._any_waiter: asyncio.Future[None] | None = None
        self._closed = False
        self.published = 0
        self.delivered = 0
        self._served = 0

    # --- life cycle ------------------------------------------------------------------------

    async def __aenter__(self) -> Node:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def node_id(self) -> int:
        if self._node_id is None:
            raise ConfigError("the node id is chosen when the node starts")
        return self._node_id

    @property
    def face(self) -> Face:
        if self._face is None:
            raise Closed("node not started")
        return self._face

    async def start(self) -> None:
        """Open the network and join it (on CAN: obtain a TxNode from the CAN-ECB; on TCP/IP:
        register with the TCP-ECB)."""
        if self._face is not None:
            return
        if self._node_id is None:
            # With TLS the identity is part of it: one program run by two identities on one
            # machine gets two ids (the TCP-ECB binds each id to one identity).
            key = self.name if self._tls is None else f"{self.name}\0{self._tls.identity()}"
            self._node_id, self._id_lock = claim_node_id(key)
        context = FaceContext(self._node_id, self.name, self._deliver, self._states, self.stats,
                              self._join_timeout)  # fmt: skip
        face = build_face(self._network, self._where, context, self._options)
        bound = "" if self._join_timeout is None else f" (up to {self._join_timeout:g} s)"
        waiting = asyncio.get_running_loop().call_later(
            1.0, log.warning, "waiting for %s%s", face.where, bound if self._join_timeout else ""
        )  # a second of silence is long enough to say why
        try:
            await face.start()
        except BaseException as exc:
            await face.close()
            self._release_id()
            raise exc  # named: compiled (mypyc), a bare raise after an await raised another
        finally:
            waiting.cancel()
        self._face = face

    async def close(self) -> None:
        """Close every subscription and the network. Safe to call twice."""
        if self._closed:
            return
        face = self._face
        if face is not None:  # withdraw our subscriptions, so nobody forwards to us in vain
            for state in self._states.values():
                if state.subs:
                    state.subs.clear()
                    with contextlib.suppress(Exception):
                        await face.unsubscribe(state)
        self._closed = True
        self._watching.close()
        for sub in self._subs:
            sub._close()
        self._subs.clear()
        self._wake_any()
        if face is not None:
            await face.close()
        self._release_id()

    def _release_id(self) -> None:
        if self._id_lock is not None:
            self._id_lock.close()
            self._id_lock = None

    # --- the four primitives -------------------------------------------------------------

    async def publish(
        self, channel: ChannelLike, data: bytes | bytearray | memoryview, *, wait: bool = False
    ) -> None:
        """Publish ``data`` on ``channel``: to local subscribers at once, and on the network.

        Never blocks by default: what a subscriber cannot take is dropped and counted. With
        ``wait=True`` it first waits until every subscriber's queue has room (backpressure, on
        TCP/IP: a publisher that outpaces its subscribers slows down instead of dropping).
        Raises ``PayloadTooLarge`` when ``data`` is larger than the network carries (65535
        bytes on CAN, 1 MiB on TCP/IP and Zenoh). On CAN, the first event larger than the channel's
        binding allows moves the channel to a larger size class first (``advertise`` with
        ``max_size`` avoids that pause).
        """
        if self._closed:
            raise Closed("node closed")
        state = self._publishing.get(channel)  # keyed as the caller names it: no re-hashing
        if state is None:
            state = self._publishing[channel] = await self._publishing_state(channel)
        payload = bytes(data)
        face = self._face
        assert face is not None
        if len(payload) > state.max_size:  # on CAN: a larger size class, bound once
            await face.grow(state, len(payload))
        if wait:
            await face.room(state)
        self.publish_nowait(channel, payload)  # bound now, for events this large

    def publish_nowait(self, channel: ChannelLike, data: bytes | bytearray | memoryview) -> None:
        """``publish`` without awaiting, for callbacks and tight loops: the channel must be
        bound already (``advertise``, or an earlier ``publish``), for events this large.

        Raises ``ConfigError`` when it is not; never blocks, never waits for room (what a
        subscriber cannot take is dropped and counted, as with ``publish``).
        """
        state = self._publishing.get(channel)
        payload = bytes(data)
        if state is None or len(payload) > state.max_size or self._closed:
            state = self._bound(channel, len(payload))
        self.published += 1
        if state.subs:
            self._deliver(state, payload, state.priority, None, time.time())
        self._face.send(state, payload, state.priority)  # type: ignore[union-attr]

    def _bound(self, channel: ChannelLike, size: int) -> ChannelState:
        """``channel``'s state, if it is bound for publishing events of ``size`` bytes."""
        self._check_open()
        state = self._states.get(as_channel(channel).uid)
        if state is None or not state.published:
            raise ConfigError(f"{channel!r} is not bound yet: await advertise() first")
        if size > state.max_size:
            raise ConfigError(
                f"{size} bytes is more than {state.channel}'s binding carries "
                f"({state.max_size}): await advertise(..., max_size={size}) first"
            )
        self._publishing[channel] = state  # named this way too, from now on
        return state

    async def advertise(self, channel: ChannelLike, *, max_size: int = 0) -> None:
        """Bind ``channel`` for publishing now, so that the first ``publish`` is not delayed by
        the network's binding (a round trip to the CAN-ECB or the TCP-ECB). ``publish`` binds
        by itself when this was not called. ``max_size``: the largest event to come (on CAN,
        it picks the channel's size class now, and subscribers learn it before any event)."""
        if self._closed:
            raise Closed("node closed")
        state = self._publishing.get(channel)
        if state is None:
            state = self._publishing[channel] = await self._publishing_state(channel, max_size)
        if max_size > state.max_size:
            await self.face.grow(state, max_size)

    async def subscribe(
        self,
        *channels: ChannelLike,
        maxlen: int = DEFAULT_QUEUE,
        overflow: Overflow = "drop_oldest",
        callback: Callable[[Message], object] | None = None,
    ) -> Subscription:
        """Subscribe to one or more channels; events arrive in the returned Subscription, or
        (with ``callback``) are handed to ``callback(msg)`` as they arrive, without a queue.

        A name holding ``*``, ``?`` or ``[`` is a pattern (a glob over names: ``_channel``): the
        subscription gets every channel whose name matches, named now or later (by the TCP-ECB;
        in Zenoh keys, with a channel's first event; on CAN, by the ``catalog``). Where no names
        are known (CAN without a catalog) it raises ``ConfigError``."""
        self._check_open()
        if not channels:
            raise ConfigError("subscribe needs at least one channel")
        if maxlen < 1:
            raise ConfigError(f"maxlen must be at least 1, got {maxlen}")
        if overflow not in OVERFLOWS:
            raise ConfigError(f"overflow must be one of {OVERFLOWS}, got {overflow!r}")
        patterns = tuple(dict.fromkeys(check_pattern(c) for c in channels if is_pattern(c)))
        chans = tuple(dict.fromkeys(as_channel(c) for c in channels if not is_pattern(c)))
        sub = Subscription(self.unsubscribe, chans, maxlen, overflow, callback, patterns)
        attached: list[Channel] = []
        try:
            for chan in chans:
                await self._attach(chan, sub)
                attached.append(chan)
            if patterns:
                await self._watching.add(sub)
        except BaseException as exc:  # e.g. AccessDenied for one of them: take back the others
            sub._close()
            for chan in attached + [c for c in sub.channels if c not in chans]:
                await self._detach(chan, sub)
            raise exc  # named, as in start
        self._subs.append(sub)
        return sub

    async def unsubscribe(self, target: Subscription | ChannelLike) -> None:
        """End a subscription, or every subscription of this node to a channel (or pattern)."""
        if isinstance(target, Subscription):
            subs = [target]
        elif is_pattern(target):
            subs = [s for s in self._subs if target in s.patterns]
        else:
            state = self._states.get(as_channel(target).uid)
            subs = [s for s in state.subs if isinstance(s, Subscription)] if state else []
        for sub in subs:
            if sub._closed:
                continue
            sub._close()
            with contextlib.suppress(ValueError):
                self._subs.remove(sub)
            for chan in sub.channels:
                await self._detach(chan, sub)
            if sub.patterns:
                await self._watching.remove(sub)

    async def get_msg(self, timeout: float | None = None) -> Message:
        """The next event from any of this node's subscriptions, oldest first.

        Raises ``TimeoutError`` after ``timeout`` seconds and ``Closed`` once the node closed.
        """
        self._served += 1
        if self._served >= YIELD_EVERY:  # draining deep queues still lets the loop run
            self._served = 0
            await asyncio.sleep(0)
        while True:
            oldest: Subscription | None = None
            for sub in self._subs:
                if sub._queue and (
                    oldest is None or sub._queue[0].timestamp < oldest._queue[0].timestamp
                ):
                    oldest = sub
            if oldest is not None:
                return oldest._queue.popleft()
            self._check_open()
            loop = asyncio.get_running_loop()
            waiter = loop.create_future()
            self._any_waiter = waiter
            try:
                await wait(loop, waiter, timeout)
            finally:
                self._any_waiter = None

    async def declare(
        self,
        channel: ChannelLike,
        *,
        period_ms: float,
        deadline_ms: float,
        size_bytes: int = 8,
        jitter_ms: float = 0.0,
    ) -> int:
        """Declare ``channel`` a real-time channel that this node publishes on (CAN only).

        At most one event of ``size_bytes`` every ``period_ms``, released up to ``jitter_ms``
        late, each due on the bus within ``deadline_ms``. The CAN-ECB admits the stream only if
        every declared stream of the bus stays schedulable (worst-case response-time analysis,
        Davis et al. 2007), and then sets its priority (returned; from then on publishing uses
        it). Otherwise it raises ``Unschedulable`` naming the channel that would miss its
        deadline. Times are rounded to 0.1 ms, towards the safe side.
        """
        self._check_open()
        declare = getattr(self.face, "declare", None)  # a CAN face's: the CAN-ECB admits
        if declare is None:
            raise ConfigError("real-time declarations are for CAN channels")
        state = await self._publishing_state(channel)
        priority: int = await declare(state, size_bytes, period_ms, deadline_ms, jitter_ms)
        state.declared = True
        return priority

    # --- settings and statistics ----------------------------------------------------------

    def set_priority(self, channel: ChannelLike, priority: int) -> None:
        """Set the priority this node publishes ``channel`` with (0 highest .. 255 lowest).

        Declared real-time channels get theirs from the CAN-ECB; best-effort channels should
        stay in 0x80..0xFF, below every declared one (0x02..0x7F). On CAN, 0x00 and 0x01
        belong to management frames: an event asking for them is sent at 0x02.
        """
        if not 0 <= priority <= 0xFF:
            raise ConfigError(f"priority must be 0..255, got {priority}")
        uid = as_channel(channel).uid
        if uid in self._states and self._states[uid].declared:
            raise ConfigError(
                f"{self._states[uid].channel} is declared: the CAN-ECB sets its priority"
            )
        self._priorities[uid] = priority
        if uid in self._states:
            self._states[uid].priority = priority

    def stats(self) -> dict[str, int]:
        """Counters: events published, delivered, dropped in full queues, and the face's own."""
        counters = {
            "published": self.published,
            "delivered": self.delivered,
            "dropped": sum(sub.dropped for sub in self._subs),
            "callback_errors": sum(sub.errors for sub in self._subs),
            **self._watching.counters,
        }
        if self._face is not None:
            counters.update(self._face.stats())
        return counters

    # --- internals ------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise Closed("node closed")
        if self._face is None:
            raise Closed("node not started: use 'async with Node(...)' or 'await node.start()'")

    def _state(self, chan: Channel) -> ChannelState:
        state = self._states.get(chan.uid)
        if state is None:
            priority = self._priorities.get(chan.uid, DEFAULT_PRIORITY)
            state = self._states[chan.uid] = ChannelState(chan, priority)
            if chan.name is not None and self._watching.active:  # a name used here: after
                asyncio.get_running_loop().call_soon(self._watching.found, chan)  # this bind
        return state

    async def _attach(self, chan: Channel, sink: Sink) -> ChannelState:
        """Deliver ``chan``'s events to ``sink`` too (subscribing on the network if need be)."""
        state = self._state(chan)
        first = not state.subs
        state.subs.append(sink)  # events that come while the network binds are kept too
        if first:
            try:
                await self.face.bind(state, subscribe=True)
            except BaseException:
                state.subs.remove(sink)
                raise
        return state

    async def _detach(self, chan: Channel, sink: Sink) -> None:
        state = self._states[chan.uid]
        state.subs.remove(sink)
        if not state.subs and self._face is not None and not self._closed:
            await self._face.unsubscribe(state)

    async def _publishing_state(self, channel: ChannelLike, size: int = 0) -> ChannelState:
        self._check_open()
        state = self._state(as_literal(channel))  # a pattern is refused
        if not state.published:
            await self.face.bind(state, subscribe=False, size=size)
            state.published = True
        return state

    def _deliver(
        self, state: ChannelState, data: bytes, priority: int, source: int | None, ts: Any
    ) -> None:
        """Hand one event to every local subscription of its channel (the face calls this).
        ``ts`` is a float; Any, so that the compiled build puts the face's float object in the
        message as it is instead of making a new one per event."""
        msg: Message = _new_message(Message, (state.channel, data, ts, priority, source))
        for sub in state.subs:
            sub._push(msg)
        self.delivered += 1
        if self._any_waiter is not None:
            self._wake_any()

    def _wake_any(self) -> None:
        waiter = self._any_waiter
        if waiter is not None:
            self._any_waiter = None
            if not waiter.done():
                waiter.set_result(None)


def _program_name() -> str:
    return Path(sys.argv[0]).name or "python"
