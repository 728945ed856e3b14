"""The CAN face of a node: joining the bus, binding channels to etags, sending and filtering.

See docs/protocol.md for the frames. The join is a race over the node's 64-bit id, nibble by
nibble, refereed by the CAN-ECB: the lowest id among simultaneous joiners always wins, the
others start again, and a node restarting gets its old TxNode back.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import TYPE_CHECKING, Any

import can

from . import _canproto as p
from ._canlink import CanLink
from ._errors import BrokerUnavailable, ConfigError, DecodeError, Exhausted, Unschedulable

if TYPE_CHECKING:
    from ._node import ChannelState, Node

log = logging.getLogger("ups.can")

_RETRY_FIRST = 0.05  # seconds before asking the CAN-ECB again
_RETRY_MAX = 1.0
_BIND_TIMEOUT = 5.0
_ANNOUNCE_GAP = 0.001  # pacing of the burst of announcements after a CAN-ECB restart
_MGMT_FILTER = {
    "can_id": p.MGMT_TXNODE << p.TXNODE_SHIFT,
    "can_mask": p.TXNODE_MASK << p.TXNODE_SHIFT,
    "extended": True,
}


class CanFace:
    """A node's face on one CAN bus (any python-can interface)."""

    max_payload = p.CLASSIC_MAX_DATA

    def __init__(
        self,
        node: Node,
        bus: str | can.BusABC | CanLink,
        node_id: int,
        join_timeout: float | None,
        filter_limit: int,
    ) -> None:
        self._node = node
        self._handler = self._on_frame  # one bound method, so the link can tell it apart
        if isinstance(bus, CanLink):
            self.link = bus
            self._owns_link = False
        elif isinstance(bus, can.BusABC):
            self.link = CanLink(bus, owns_bus=False)
            self._owns_link = True
        elif isinstance(bus, str):
            self.link = CanLink.open(bus)
            self._owns_link = True
        else:
            raise ConfigError(f"can= takes 'INTERFACE:CHANNEL' or a python-can bus, not {bus!r}")
        self.node_id = node_id
        self.txnode: int | None = None
        self._nibbles = p.nibbles_of(node_id)
        self._join_timeout = join_timeout
        self._filter_limit = filter_limit
        self._etag_of: dict[int, int] = {}  # uid -> etag, every binding heard on the bus
        self._uid_of: dict[int, int] = {}  # etag -> uid
        self._rx: dict[int, ChannelState] = {}  # etag -> channel with local subscribers
        self._pending: dict[int, asyncio.Future[int]] = {}  # uid -> etag awaited
        self._joined: asyncio.Future[int] | None = None
        self._offer: p.Stage | None = None
        self._answered: tuple[int, int] | None = None
        self._announcer: asyncio.Task[None] | None = None
        self._declared: dict[int, tuple[int, int, int, int]] = {}  # uid -> size, T, D, J
        self._verdicts: dict[int, asyncio.Future[int]] = {}  # etag -> granted priority
        self.counters = dict.fromkeys(
            ("sent", "foreign", "unknown", "filtered", "own_echo", "malformed", "tx_failed"), 0
        )

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        self.link.add_handler(self._handler, [_MGMT_FILTER])
        self.link.start()
        self.txnode = await self._join()
        log.info(
            "node %016x joined %s as TxNode %d", self.node_id, self.link.channel_info, self.txnode
        )

    async def close(self) -> None:
        if self._announcer is not None:
            self._announcer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._announcer
        for fut in [*self._pending.values(), *self._verdicts.values()]:
            fut.cancel()
        self.link.remove_handler(self._handler)
        if self._owns_link:
            self.link.close()

    def stats(self) -> dict[str, int]:
        return {
            **self.counters,
            "tx_failed": self.link.tx_failed,
            "bindings": len(self._etag_of),
            "txnode": -1 if self.txnode is None else self.txnode,
        }

    # --- the Face protocol -----------------------------------------------------------------

    async def bind(self, state: ChannelState, subscribe: bool) -> None:
        uid = state.channel.uid
        kind = p.SUB_BIND if subscribe else p.PUB_BIND
        etag = self._etag_of.get(uid)
        if etag is None:
            etag = await self._request_etag(kind, uid)
        else:  # bound already: tell the CAN-ECB, but the bus works without waiting for it
            self._send(p.Request(kind, self._my_txnode(), uid))
        if subscribe:
            self._rx[etag] = state
            self._update_filters()

    async def unsubscribe(self, state: ChannelState) -> None:
        uid = state.channel.uid
        etag = self._etag_of.get(uid)
        if etag is not None and self._rx.get(etag) is state:
            del self._rx[etag]
            self._update_filters()
        self._send(p.Request(p.UNSUB, self._my_txnode(), uid))

    def send(self, state: ChannelState, data: bytes, priority: int) -> None:
        etag = self._etag_of[state.channel.uid]
        can_id = (priority << p.PRIORITY_SHIFT) | (self.txnode << p.TXNODE_SHIFT) | etag  # type: ignore[operator]
        if self.link.send(can_id, data, self._handler):
            self.counters["sent"] += 1

    # --- receiving -------------------------------------------------------------------------

    def _on_frame(self, frame: can.Message) -> None:
        if not frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame or frame.is_fd:
            self.counters["foreign"] += 1
            return
        can_id = frame.arbitration_id
        etag = can_id & p.ETAG_MASK
        txnode = (can_id >> p.TXNODE_SHIFT) & p.TXNODE_MASK
        if txnode == p.MGMT_TXNODE or etag < p.FIRST_ETAG:
            self._on_management(can_id, bytes(frame.data))
            return
        state = self._rx.get(etag)
        if state is None:
            self.counters["filtered" if etag in self._uid_of else "unknown"] += 1
        elif txnode == self.txnode:
            self.counters["own_echo"] += 1
        else:
            self._node._deliver(
                state, bytes(frame.data), can_id >> p.PRIORITY_SHIFT, txnode, frame.timestamp
            )

    def _on_management(self, can_id: int, data: bytes) -> None:
        try:
            msg = p.decode(can_id, data)
        except DecodeError as exc:
            self.counters["malformed"] += 1
            log.debug("skipped malformed management frame: %s", exc)
            return
        if isinstance(msg, p.Bind):
            self._on_bind(msg.etag, msg.uid)
        elif isinstance(msg, p.EtagsFull):
            fut = self._pending.pop(msg.uid, None)
            if fut is not None and not fut.done():
                fut.set_exception(Exhausted(f"the CAN-ECB has no etag left for {msg.uid:#018x}"))
        elif isinstance(msg, p.Grant | p.Refuse):
            if msg.txnode == self.txnode:
                self._on_verdict(msg)
        elif isinstance(msg, p.Hello) and self.txnode is not None:
            self._announce_all()
        elif isinstance(msg, p.Assign) and self.txnode is not None:
            if msg.node_id == self.node_id and msg.txnode != self.txnode:
                log.warning("CAN-ECB moved this node from TxNode %d to %d", self.txnode, msg.txnode)
                self.txnode = msg.txnode
        elif self._joined is not None and not self._joined.done():
            self._on_race(msg)

    def _on_bind(self, etag: int, uid: int) -> None:
        old_etag = self._etag_of.get(uid)
        old_uid = self._uid_of.get(etag)
        if old_uid is not None and old_uid != uid:  # etag re-bound: the ECB lost its tables
            del self._etag_of[old_uid]
        if old_etag is not None and old_etag != etag:
            del self._uid_of[old_etag]
            state = self._rx.pop(old_etag, None)
            if state is not None:
                self._rx[etag] = state
                self._update_filters()
        self._etag_of[uid] = etag
        self._uid_of[etag] = uid
        fut = self._pending.pop(uid, None)
        if fut is not None and not fut.done():
            fut.set_result(etag)

    # --- real-time declarations ------------------------------------------------------------

    async def declare(
        self, state: ChannelState, size: int, period_ms: float, deadline_ms: float, jitter_ms: float
    ) -> int:
        unit = p.TIME_UNIT_US / 1000
        period, deadline = int(period_ms / unit), int(deadline_ms / unit)  # round down: safe
        jitter = -int(-jitter_ms // unit)  # round up: safe
        if not 0 <= size <= p.CLASSIC_MAX_DATA:
            raise ConfigError(f"size_bytes must be 0..{p.CLASSIC_MAX_DATA}, got {size}")
        if not (1 <= period <= 0xFFFF and 1 <= deadline <= 0xFFFF and 0 <= jitter <= 0xFF):
            raise ConfigError(
                "period and deadline must be 0.1..6553.5 ms, jitter 0..25.5 ms; got "
                f"{period_ms}, {deadline_ms}, {jitter_ms}"
            )
        uid = state.channel.uid
        self._declared[uid] = (size, period, deadline, jitter)
        etag = self._etag_of[uid]
        fut = self._verdicts[etag] = asyncio.get_running_loop().create_future()
        msg = p.Declare(self._my_txnode(), etag, size, period, deadline, jitter)
        try:
            priority = await self._ask(msg, fut, f"admit {state.channel}")
        except BaseException:  # refused, unanswered or cancelled: nothing to re-announce
            self._declared.pop(uid, None)
            raise
        state.priority = priority
        return priority

    def _on_verdict(self, msg: p.Grant | p.Refuse) -> None:
        uid = self._uid_of.get(msg.etag)
        fut = self._verdicts.pop(msg.etag, None)
        if isinstance(msg, p.Grant):
            state = self._node._states.get(uid) if uid is not None else None
            if state is not None:  # also when another node's declaration moved ours
                state.priority = msg.priority
            if fut is not None and not fut.done():
                fut.set_result(msg.priority)
            return
        if fut is None or fut.done():
            return
        if (msg.miss_etag, msg.miss_txnode) == (msg.etag, msg.txnode):
            culprit = "it"
        else:
            other = self._uid_of.get(msg.miss_etag)
            name = f"0x{other:016x}" if other is not None else f"etag {msg.miss_etag:#x}"
            culprit = f"channel {name} of TxNode {msg.miss_txnode}"
        if msg.response_10us == p.RESPONSE_UNBOUNDED:
            response = "no bounded response time"
        else:
            response = f"worst-case response {msg.response_10us / 100:g} ms"
        channel = f"0x{uid:016x}" if uid is not None else f"etag {msg.etag:#x}"
        fut.set_exception(
            Unschedulable(
                f"the CAN-ECB refused real-time channel {channel}: with it, {culprit} would "
                f"miss its deadline ({response})"
            )
        )

    # --- joining: the TxNode race ----------------------------------------------------------

    async def _join(self) -> int:
        loop = asyncio.get_running_loop()
        self._joined = loop.create_future()
        self._make_offer(0, 0)
        deadline = None if self._join_timeout is None else loop.time() + self._join_timeout
        delay = _RETRY_FIRST
        while True:
            try:
                return await asyncio.wait_for(asyncio.shield(self._joined), delay)
            except TimeoutError:
                pass
            if deadline is not None and loop.time() >= deadline:
                raise BrokerUnavailable(
                    f"no CAN-ECB answered on {self.link.channel_info} within "
                    f"{self._join_timeout:g} s; start one with 'ups can-broker --can ...' "
                    "or a gateway"
                )
            delay = min(delay * 2, _RETRY_MAX)
            self._answered = None
            if self._offer is not None:  # ask again: a stale offer makes the ECB repeat its state
                self._send(self._offer)

    def _on_race(self, msg: p.Management) -> None:
        assert self._joined is not None
        if isinstance(msg, p.Reset | p.Hello):
            self._answer(msg.epoch, 0, 0)
        elif isinstance(msg, p.Ack):
            prefix = msg.prefix
            mine = self._nibbles[: len(prefix)]
            if prefix == mine:
                if len(prefix) < p.NIBBLES:
                    self._answer(msg.epoch, len(prefix), len(prefix))
            else:
                d = next(i for i, (a, b) in enumerate(zip(prefix, mine, strict=True)) if a != b)
                if prefix[d] > mine[d]:  # the leader's id is higher: claim the lead at d
                    self._answer(msg.epoch, len(prefix), d)
                # else: a lower id leads; wait for the next race
        elif isinstance(msg, p.Assign) and msg.node_id == self.node_id:
            self._joined.set_result(msg.txnode)
        elif isinstance(msg, p.TxNodesFull) and msg.node_id == self.node_id:
            self._joined.set_exception(
                Exhausted(f"all {p.TXNODE_COUNT} TxNodes of {self.link.channel_info} are taken")
            )

    def _answer(self, epoch: int, state_len: int, stage: int) -> None:
        """Answer one ECB state once: repeats of it (caused by others) are not answered again."""
        if self._answered == (epoch, state_len):
            return
        self._answered = (epoch, state_len)
        self._make_offer(epoch, stage)

    def _make_offer(self, epoch: int, stage: int) -> None:
        self._offer = p.Stage(epoch, stage, self._nibbles[stage])
        self._send(self._offer)

    # --- binding ---------------------------------------------------------------------------

    async def _request_etag(self, kind: int, uid: int) -> int:
        fut = self._pending.get(uid)
        if fut is None:
            fut = self._pending[uid] = asyncio.get_running_loop().create_future()
        try:
            return await self._ask(
                p.Request(kind, self._my_txnode(), uid), fut, f"bind {uid:#018x}"
            )
        finally:
            if self._pending.get(uid) is fut and not fut.done():
                del self._pending[uid]

    async def _ask(self, msg: p.Management, fut: asyncio.Future[int], what: str) -> int:
        """Send ``msg`` until ``fut`` has the CAN-ECB's answer: 50 ms, doubling, 5 s in all."""
        delay = _RETRY_FIRST
        waited = 0.0
        while True:
            self._send(msg)
            try:
                return await asyncio.wait_for(asyncio.shield(fut), delay)
            except TimeoutError:
                waited += delay
                if waited >= _BIND_TIMEOUT:
                    raise BrokerUnavailable(
                        f"the CAN-ECB on {self.link.channel_info} did not {what} "
                        f"within {_BIND_TIMEOUT:g} s"
                    ) from None
                delay = min(delay * 2, _RETRY_MAX)

    def _announce_all(self) -> None:
        """After a CAN-ECB (re)start: claim our TxNode again and re-announce every channel."""
        if self._announcer is None or self._announcer.done():
            self._announcer = asyncio.get_running_loop().create_task(self._announce())

    async def _announce(self) -> None:
        txnode = self._my_txnode()
        self._send(p.Request(p.CLAIM, txnode, self.node_id))
        for state in list(self._node._states.values()):
            uid = state.channel.uid
            if state.subs:
                await asyncio.sleep(_ANNOUNCE_GAP)
                self._send(p.Request(p.SUB_BIND, txnode, uid))
            if state.published:
                await asyncio.sleep(_ANNOUNCE_GAP)
                self._send(p.Request(p.PUB_BIND, txnode, uid))
            if uid in self._declared and uid in self._etag_of:
                await asyncio.sleep(_ANNOUNCE_GAP)
                size, period, deadline, jitter = self._declared[uid]
                etag = self._etag_of[uid]
                self._send(p.Declare(txnode, etag, size, period, deadline, jitter))

    # --- helpers ---------------------------------------------------------------------------

    def _my_txnode(self) -> int:
        assert self.txnode is not None, "node has not joined the bus"
        return self.txnode

    def _send(self, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        self.link.send(can_id, data, self._handler)

    def _update_filters(self) -> None:
        filters: list[dict[str, Any]] | None = None
        if len(self._rx) <= self._filter_limit:
            filters = [_MGMT_FILTER]
            filters += [
                {"can_id": etag, "can_mask": p.ETAG_MASK, "extended": True} for etag in self._rx
            ]
        self.link.set_filters(self._handler, filters)
