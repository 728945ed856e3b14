"""The CAN face of a node: joining the bus (``_canjoin``), binding channels to etags (its table
in ``_canbinding``; binding again after a contradiction in ``_canrebind``), sending, receiving
and filtering (the filters and the reassembly of transfers in ``_canrx``).

See docs/protocol.md for the frames. A node relies only on bindings the CAN-ECB gave in answer
to its own request. Any Bind that contradicts one of them (another UID on the etag, or another
etag for the UID) makes the node drop both, stop delivering and sending on them, and ask the
CAN-ECB again: no event of one channel is ever delivered as another.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from pathlib import Path

import can

from . import _canproto as p
from . import _cantransfer as t
from ._canannounce import Announcer
from ._canbinding import SETTLE, Bindings
from ._canjoin import Joiner
from ._canlink import CanLink
from ._canrebind import Rebinding
from ._canrx import MGMT_FILTER, Transfers, filters
from ._canstreams import Streams, declaration
from ._catalog import Catalog
from ._errors import (
    BrokerUnavailable,
    ConfigError,
    DecodeError,
    Exhausted,
    PayloadTooLarge,
)
from ._face import ChannelState, Deliver, FaceContext, Found

log = logging.getLogger("ups.can")

_LOG_GAP = 10.0
#: a publisher waits this long before its first event on a channel of a larger size class (its
#: binding may have just moved the channel there): the subscribers, who see their binding
#: contradicted, bind it again and let the answer settle meanwhile, and receive that event
_GROW_PAUSE = 3 * SETTLE
_STAGE_MASK = p.make_id(0xFF, 0x7F, 0x3000)
_STAGE_ID = p.make_id(p.CONFIG_PRIORITY, p.MGMT_TXNODE, 0)


#: the Node options a CAN face takes (see ``Node``)
OPTIONS = frozenset({"filter_limit", "max_event", "catalog"})


def build(
    bus: str | can.BusABC | CanLink,
    context: FaceContext,
    *,
    filter_limit: int = 16,
    max_event: int = t.MAX_EVENT,
    catalog: str | Path | Catalog | None = None,
) -> CanFace:
    face = CanFace(
        bus,
        context.node_id,
        deliver=context.deliver,
        channels=context.channels,
        join_timeout=context.join_timeout,
        filter_limit=filter_limit,
        max_event=max_event,
    )
    face.catalog = Catalog.load(catalog) if isinstance(catalog, str | Path) else catalog
    return face


class CanFace:
    """A node's face on one CAN bus (any python-can interface)."""

    max_payload = t.MAX_EVENT

    def __init__(
        self,
        bus: str | can.BusABC | CanLink,
        node_id: int,
        *,
        deliver: Deliver,
        channels: dict[int, ChannelState],
        join_timeout: float | None,
        filter_limit: int,
        max_event: int = t.MAX_EVENT,
    ) -> None:
        self._deliver = deliver
        self._channels = channels
        self._handler = self._on_frame  # one bound method, so the link can tell it apart
        if isinstance(bus, CanLink):
            self.link = bus
            self._owns_link = False
        elif isinstance(bus, can.BusABC):
            self.link = CanLink(bus, owns_bus=False)
            self._owns_link = True
        elif isinstance(bus, str):  # one connection per bus for all the nodes of the process
            self.link = CanLink.shared(bus)
            self._owns_link = True
        else:
            raise ConfigError(f"can= takes 'INTERFACE:CHANNEL' or a python-can bus, not {bus!r}")
        self.node_id = node_id
        #: where channel names come from on CAN (frames carry none): for pattern subscriptions
        self.catalog: Catalog | None = None
        self.where = f"the CAN-ECB on {self.link}"
        self.txnode: int | None = None
        self._joiner = Joiner(node_id, self._send, self.link.channel_info, join_timeout)
        self._filter_limit = filter_limit
        self._max_event = max_event  # the largest event this node buffers
        self._tids: dict[int, int] = {}  # etag -> transfer id of this node's next event
        self._growing: dict[int, asyncio.Future[None]] = {}  # uid -> its move to a larger class
        self._rx: dict[int, ChannelState] = {}  # etag -> channel with local subscribers
        self._suspended: set[int] = set()  # etags received but no longer relied on: counted
        self._wants_rx: dict[int, ChannelState] = {}  # uid -> subscribed channel being bound
        self._logged: dict[str, float] = {}
        self._transfers = Transfers(self._warn)  # events larger than a frame, reassembled
        self.counters = dict.fromkeys(
            ("sent", "foreign", "unknown", "filtered", "own_echo", "malformed", "tx_failed",
             "rebinds", "moves", "reassigned", "unbound_dropped", "task_errors", "too_large",
             "refused_large", "stray_verdicts", "refusals", "stray_refusals"),
            0,
        )  # fmt: skip
        self._rebinding: dict[int, asyncio.Task[None]] = {}  # uid -> its task (_canrebind)
        self.bindings = Bindings(
            send=self._send, txnode=self._my_txnode, bus=str(self.link.channel_info),
            counters=self.counters, warn=self._warn, on_adopted=self._adopted,
            on_contradicted=self._suspend, rebinding=self._rebinding,
        )  # fmt: skip
        self._rebinder = Rebinding(
            self._rebinding, bindings=self.bindings, wants_rx=self._wants_rx,
            receive=self._accept, send=self._send, txnode=self._my_txnode,
            counters=self.counters, warn=self._warn,
        )  # fmt: skip
        self.streams = Streams(
            send=self._send, txnode=self._my_txnode, uid_at=self.bindings.uid_at,
            heard=self.bindings.heard, counters=self.counters, warn=self._warn,
            bus=str(self.link.channel_info),
        )  # fmt: skip
        self._announcer = Announcer(
            send=self._send, node_id=node_id, txnode=lambda: self.txnode, channels=channels,
            bound=self.bindings.bound, declared=self.streams.declared, counters=self.counters,
        )  # fmt: skip

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        self.link.add_handler(self._handler, [MGMT_FILTER])
        self.link.start()
        self.txnode = await self._joiner.run()
        node_id, bus = self.node_id, self.link.channel_info
        log.info("node %016x joined %s as TxNode 0x%02x", node_id, bus, self.txnode)

    async def close(self) -> None:
        task = self._announcer.task
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self._rebinder.close()
        self.streams.close()
        self.bindings.close()
        self._transfers.close()
        await self.link.flush()  # the frames of transfers still waiting for the interface
        self.link.remove_handler(self._handler)
        if self._owns_link:
            self.link.release()

    def stats(self) -> dict[str, int]:
        return {
            **self.counters,
            "refusals": self.counters["refusals"] + self._joiner.refusals,
            "tx_failed": self.link.tx_failed,
            "large_lost": self._transfers.reassembler.lost,
            "large_frames_dropped": self._transfers.reassembler.frames_dropped,
            "bindings": len(self.bindings.bound),
            "txnode": -1 if self.txnode is None else self.txnode,
        }

    # --- the Face protocol -----------------------------------------------------------------

    async def bind(self, state: ChannelState, subscribe: bool, size: int = 0) -> None:
        uid, bound = state.channel.uid, self.bindings.bound
        etag = bound.get(uid)
        if etag is not None:  # confirmed already: tell the CAN-ECB our role; it corrects us
            self._send(p.Holds(not subscribe, self._my_txnode(), etag, uid))
        while True:
            while etag is None or bound.get(uid) != etag:  # a contradiction came meanwhile
                if subscribe:  # receive from the moment the Bind is handled, not a loop later
                    self._wants_rx[uid] = state
                try:
                    kind, cls = (
                        (p.SUB_BIND, 0)
                        if subscribe
                        else (p.PUB_BIND, t.class_for(min(size, t.MAX_EVENT)))
                    )
                    etag = await self.bindings.request(kind, uid, cls)
                finally:
                    self._wants_rx.pop(uid, None)
            state.max_size = t.max_size(etag)
            if subscribe:
                self._accept(etag, state)
                return
            if etag < p.LARGE_FIRST_ETAG or state.published:
                return
            await asyncio.sleep(_GROW_PAUSE)  # it may have moved just now: see _GROW_PAUSE
            if bound.get(uid) == etag:
                return
            # contradicted during the pause: _suspend started no re-bind (the channel is
            # ``published`` only once this returns), so bind it here

    async def grow(self, state: ChannelState, size: int) -> None:
        """Move the channel to the smallest size class that carries ``size`` bytes: ask the
        CAN-ECB (PUB_BIND of that class), rely on the new etag, and pause ``_GROW_PAUSE`` so
        that the subscribers, who see the old binding contradicted, bind it again first."""
        if size > t.MAX_EVENT:
            raise PayloadTooLarge(
                f"{size} bytes do not fit one event on {state.channel} (at most {t.MAX_EVENT} "
                "on CAN)"
            )
        uid = state.channel.uid
        while size > state.max_size:
            moving = self._growing.get(uid)
            if moving is not None:  # another publish moves it already
                await asyncio.shield(moving)
                continue
            moving = self._growing[uid] = asyncio.get_running_loop().create_future()
            try:
                await self._move(state, t.class_for(size))
            finally:
                del self._growing[uid]
                moving.set_result(None)

    async def _move(self, state: ChannelState, cls: int) -> None:
        uid = state.channel.uid
        if state.subs and t.CLASS_MAX[cls] > self._max_event:
            raise PayloadTooLarge(
                f"{state.channel} would carry events up to {t.CLASS_MAX[cls]} bytes; this node "
                f"subscribes to it and buffers at most {self._max_event} (max_event)"
            )
        old = self.bindings.forget(uid)
        if old is not None:
            if self._rx.pop(old, None) is not None:
                self._suspended.add(old)
            self._update_filters()
        if state.subs:
            self._wants_rx[uid] = state
        try:
            etag = await self.bindings.request(p.PUB_BIND, uid, cls)
        finally:
            self._wants_rx.pop(uid, None)
        state.max_size = t.max_size(etag)
        if state.subs:
            self._send(p.Holds(False, self._my_txnode(), etag, uid))
        if t.size_class(etag) < cls:
            raise PayloadTooLarge(
                f"the CAN-ECB bound {state.channel} to etag {etag:#x}, which carries at most "
                f"{t.max_size(etag)} bytes: it does not bind larger events (an older CAN-ECB?)"
            )
        log.info("channel %s moved to etag %#x (events up to %d bytes)", state.channel, etag,
                 state.max_size)  # fmt: skip
        await asyncio.sleep(_GROW_PAUSE)

    def _accept(self, etag: int, state: ChannelState) -> None:
        """Receive ``state``'s channel, bound to ``etag``, if this node buffers its events."""
        self._check_fits(state, etag)
        self._receive(etag, state)

    def _check_fits(self, state: ChannelState, etag: int) -> None:
        """Refuse to receive a channel whose events this node would not buffer."""
        if t.max_size(etag) <= self._max_event:
            return
        self.counters["refused_large"] += 1
        if self._rx.pop(etag, None) is not None:
            self._update_filters()
        self._send(p.Request(p.UNSUB, self._my_txnode(), state.channel.uid))
        raise PayloadTooLarge(
            f"{state.channel} carries events up to {t.max_size(etag)} bytes on this bus; this "
            f"node buffers at most {self._max_event} (max_event)"
        )

    async def unsubscribe(self, state: ChannelState) -> None:
        uid = state.channel.uid
        etag = self.bindings.bound.get(uid)
        if etag is not None and self._rx.get(etag) is state:
            del self._rx[etag]
            self._update_filters()
        self._send(p.Request(p.UNSUB, self._my_txnode(), uid))

    def send(self, state: ChannelState, data: bytes, priority: int) -> None:
        etag = self.bindings.bound.get(state.channel.uid)
        if etag is None:  # being bound again after a contradiction: nothing may go out
            self.counters["unbound_dropped"] += 1
            return
        priority = max(priority, p.FIRST_EVENT_PRIORITY)
        can_id = (priority << p.PRIORITY_SHIFT) | (self._my_txnode() << p.TXNODE_SHIFT) | etag
        if etag < p.LARGE_FIRST_ETAG:  # one frame, the event as its data
            if len(data) > p.CLASSIC_MAX_DATA:
                self.counters["too_large"] += 1
            elif self.link.send(can_id, data, self._handler, self.link.fd):
                self.counters["sent"] += 1
            return
        if len(data) > t.max_size(etag):
            self.counters["too_large"] += 1
            return
        tid = self._tids.get(etag, 0)
        self._tids[etag] = (tid + 1) & t.TID_MASK
        frames = t.segment(data, tid, self.link.mtu)
        if self.link.send_transfer(can_id, frames, self._handler, self.link.fd):
            self.counters["sent"] += 1

    async def watch(self, pattern: str, found: Found) -> None:
        """On CAN names come only from the channel catalog: ``found`` gets each of its named
        channels (the node keeps those that match), once; without a catalog, ``ConfigError``."""
        if self.catalog is None:
            raise ConfigError(
                f"on CAN, channel names come only from a channel catalog: subscribing to "
                f"{pattern} needs one (--catalog FILE or $UPS_CATALOG; Node(catalog=FILE))"
            )
        for spec in self.catalog:
            if spec.name is not None:
                found(spec.channel)

    async def unwatch(self, pattern: str) -> None:
        """Nothing to undo: the catalog does not change."""

    async def room(self, state: ChannelState) -> None:
        """The interface takes frames or refuses them (counted): nothing to wait for."""

    # --- receiving -------------------------------------------------------------------------

    def receives(self, etag: int) -> bool:
        """Whether this node receives ``etag``: it relies on its binding, and subscribes."""
        return etag in self._rx

    def _on_frame(self, frame: can.Message) -> None:
        if not frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame:
            self.counters["foreign"] += 1
            return
        can_id = frame.arbitration_id
        etag = can_id & p.ETAG_MASK
        txnode = (can_id >> p.TXNODE_SHIFT) & p.TXNODE_MASK
        if txnode == p.MGMT_TXNODE or etag < p.FIRST_ETAG or can_id >> p.PRIORITY_SHIFT < 2:
            if frame.is_fd:  # management frames are classic frames
                self.counters["foreign"] += 1
                return
            if can_id & _STAGE_MASK != _STAGE_ID:
                self._on_management(can_id, bytes(frame.data))
            elif self.txnode is None:  # another joiner's Stage: ours would be the same frame
                self._joiner.heard_stage(can_id & 0xFFF)
            return
        state = self._rx.get(etag)
        if state is None:
            if etag in self._suspended or self._rebinding_subscribed(etag):
                self.counters["unbound_dropped"] += 1  # maybe ours: delivered as nothing
            else:
                self.counters["filtered" if etag in self.bindings.heard else "unknown"] += 1
        elif txnode == self.txnode:
            self.counters["own_echo"] += 1
        elif etag < p.LARGE_FIRST_ETAG:
            if len(frame.data) > p.CLASSIC_MAX_DATA:
                self.counters["malformed"] += 1
                return
            self._deliver(
                state, bytes(frame.data), can_id >> p.PRIORITY_SHIFT, txnode, frame.timestamp
            )
        else:
            self._on_transfer_frame(state, frame, txnode, etag)

    def _rebinding_subscribed(self, etag: int) -> bool:
        """``etag`` was last heard bound to a channel this node subscribes to and is binding
        again (it moved to a larger size class, say)."""
        uid = self.bindings.heard.get(etag)
        if uid is None or uid not in self._rebinding:
            return False
        state = self._channels.get(uid)
        return state is not None and bool(state.subs)

    def _on_transfer_frame(
        self, state: ChannelState, frame: can.Message, txnode: int, etag: int
    ) -> None:
        event = self._transfers.feed(frame, txnode, etag)
        if event is not None:
            self._deliver(state, event, frame.arbitration_id >> p.PRIORITY_SHIFT, txnode,
                          frame.timestamp)  # fmt: skip

    def _on_management(self, can_id: int, data: bytes) -> None:
        try:
            msg = p.decode(can_id, data)
        except DecodeError as exc:
            self.counters["malformed"] += 1
            log.debug("skipped malformed management frame: %s", exc)
            return
        if isinstance(msg, p.Bind):
            self.bindings.on_bind(msg.etag, msg.uid)
        elif self.txnode is None:
            self._joiner.on_frame(msg)
        elif isinstance(msg, p.EtagsFull):
            no_etag = Exhausted(f"the CAN-ECB has no etag left for {msg.uid:#018x}")
            self.bindings.fail(msg.uid, no_etag)
        elif isinstance(msg, p.Limit) and msg.txnode == self.txnode:
            self.bindings.fail(msg.uid, Exhausted("the CAN-ECB allows this node no more channels"))
        elif isinstance(msg, p.Failed):
            self.bindings.fail(
                msg.value,
                BrokerUnavailable(
                    f"the CAN-ECB of {self.link.channel_info} could not store the binding of "
                    f"{msg.value:#018x}: its database fails (see its log and 'ups status')"
                ),
            )
        elif isinstance(msg, p.Grant | p.Refuse):
            self.streams.on_verdict(msg)
        elif isinstance(msg, p.Hello):
            self._announcer.announce()
        elif isinstance(msg, p.Assign) and msg.node_id == self.node_id:
            self._moved(msg.txnode)

    def _moved(self, txnode: int) -> None:
        """An Assign names this node: the CAN-ECB gave it another TxNode (its CLAIM clashed with
        another node's), or its own again (a join under its id, forged or a copy of the node).
        Either way the CAN-ECB has forgotten the TxNode's channels: report them again."""
        if txnode != self.txnode:
            log.warning("CAN-ECB moved this node from TxNode %s to %d", self.txnode, txnode)
            self.txnode = txnode
            self._announcer.announce(at_once=True)  # our channels, under the new TxNode
        else:
            self.counters["reassigned"] += 1
            self._warn("reassigned", "the CAN-ECB assigned this node its TxNode %d again (a "
                       "join under its id): reporting its channels again", txnode)  # fmt: skip
            self._announcer.announce()  # our channels, which the CAN-ECB forgot

    def _adopted(self, etag: int, uid: int) -> None:
        """``uid`` is bound to ``etag`` now: receive it, if a subscription waits for that."""
        state = self._wants_rx.get(uid)
        if state is not None:
            self._receive(etag, state)

    def _receive(self, etag: int, state: ChannelState) -> None:
        self._rx[etag] = state
        self._suspended.discard(etag)
        self._update_filters()

    # --- re-binding after a contradiction ---------------------------------------------------

    def _suspend(self, uid: int) -> None:
        """Forget ``uid``'s binding: nothing is delivered or sent on it until it is bound again
        (``_canrebind``). Frames still arriving on its old etag are counted
        (``unbound_dropped``)."""
        etag = self.bindings.forget(uid)
        if etag is not None and self._rx.pop(etag, None) is not None:
            self._suspended.add(etag)
        state = self._channels.get(uid)
        if state is not None:
            self._rebinder.start(uid, state)

    # --- real-time declarations ------------------------------------------------------------

    async def declare(
        self, state: ChannelState, size: int, period_ms: float, deadline_ms: float, jitter_ms: float
    ) -> int:
        declaration(size, period_ms, deadline_ms, jitter_ms, etag=0, mtu=self.link.mtu)  # checks
        uid = state.channel.uid
        if size > state.max_size:
            await self.grow(state, size)
        etag = self.bindings.bound[uid]
        fields = declaration(size, period_ms, deadline_ms, jitter_ms, etag=etag, mtu=self.link.mtu)
        return await self.streams.declare(state, etag, fields)

    # --- helpers ---------------------------------------------------------------------------

    def _my_txnode(self) -> int:
        if self.txnode is None:
            raise ConfigError("the node has not joined the bus")
        return self.txnode

    def _send(self, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        self.link.send(can_id, data, self._handler)

    def _warn(self, key: str, text: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._logged.get(key, -_LOG_GAP) >= _LOG_GAP:
            self._logged[key] = now
            log.warning(text, *args)

    def _update_filters(self) -> None:
        etags = self._rx.keys() | self._suspended
        self.link.set_filters(self._handler, filters(etags, self._filter_limit))
