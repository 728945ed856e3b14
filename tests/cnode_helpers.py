"""The C node (libups through ``ups._cnode``) for the tests: on a python-can virtual bus beside
the real CAN-ECB (``c_nodes``), or frame by frame with a clock of its own (``Wire``)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field

import can

from ups import _canproto as p
from ups._cnode import FRAME_EXT, CNode, CNodeRunner, Event, now_ms
from ups.broker.can_ecb import CanEcb  # the one import of broker in the C node's tests

from .conftest import eventually


@dataclass
class CNodes:
    """C nodes driven by one runner, and every event they delivered (in order)."""

    runner: CNodeRunner
    nodes: list[CNode]
    got: list[tuple[CNode, Event]] = field(default_factory=list)

    def events(self, node: CNode, channel: int) -> list[bytes]:
        return [e.data for n, e in self.got if n is node and e.channel == channel]

    async def joined(self, timeout: float = 10.0) -> None:
        await eventually(lambda: all(n.txnode is not None for n in self.nodes), timeout)

    async def bound(self, node: CNode, channel: int, timeout: float = 10.0) -> int:
        """Wait until ``channel`` is bound (state 2); its etag."""
        await eventually(lambda: node.channel_state(channel) == 2, timeout)
        return node.channel_etag(channel)

    async def until(self, predicate: Callable[[], bool], timeout: float = 10.0) -> None:
        await eventually(predicate, timeout)


@contextlib.asynccontextmanager
async def c_nodes(
    bus: str, *ids: int, variant: str = "full", fd: bool = False, start: bool = True
) -> AsyncIterator[CNodes]:
    """Nodes of the compiled library on the virtual bus ``bus``, run every millisecond."""
    raw = can.Bus(interface="virtual", channel=bus.partition(":")[2])
    nodes = [CNode(i, variant=variant, fd=fd) for i in ids]
    result = CNodes(CNodeRunner(raw, nodes, lambda n, e, ts: None), nodes)
    result.runner._on_event = lambda n, e, ts: result.got.append((n, e))
    if start:
        result.runner.start_all()
    task = asyncio.get_running_loop().create_task(result.runner.run())
    try:
        yield result
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        raw.shutdown()


class Wire:
    """One C node driven frame by frame, with a clock of its own: nothing reaches it but what the
    test feeds, and nothing it queues is sent until the test drains it (a stalled controller is
    one that is not drained). ``sent`` holds every frame drained, in order, as
    ``(can_id, flags, data)``."""

    def __init__(self, node_id: int = 0xC0FFEE, *, variant: str = "full", fd: bool = False,
                 now: int = 1000) -> None:  # fmt: skip
        self.node = CNode(node_id, variant=variant, fd=fd)
        self.node_id = node_id
        self.now = now
        self.sent: list[tuple[int, int, bytes]] = []

    def feed(self, msg: p.Management) -> Event | None:
        can_id, data = p.encode(msg)
        return self.node.rx_raw(can_id, data, FRAME_EXT, self.now)

    def feed_raw(self, can_id: int, data: bytes, flags: int = FRAME_EXT) -> Event | None:
        return self.node.rx_raw(can_id, data, flags, self.now)

    def tick(self, ms: int = 1, *, drain: bool = True) -> None:
        """Let ``ms`` milliseconds pass, ticking every millisecond (and draining, unless the
        controller is stalled)."""
        for _ in range(ms):
            self.now = (self.now + 1) & 0xFFFFFFFF
            self.node.tick(self.now)
            if drain:
                self.drain()

    def drain(self) -> list[tuple[int, int, bytes]]:
        """Send everything queued; what was sent."""
        out = list(self.node.tx())
        self.sent += out
        return out

    def mgmt(self, since: int = 0) -> list[p.Management]:
        """The management frames sent (from index ``since`` of ``sent``), decoded."""
        return [p.decode(i, d) for i, _, d in self.sent[since:] if p.is_management(i)]

    def events(self, since: int = 0) -> list[tuple[int, bytes]]:
        """The event frames sent (from index ``since``): ``(can_id, data)``."""
        return [(i, d) for i, _, d in self.sent[since:] if not p.is_management(i)]

    def join(self, txnode: int = 5) -> None:
        """Knock, answer a Census, claim the Offer, take the Assign."""
        self.node.start(self.now)
        self.drain()
        self.feed(p.Census(0))
        self.drain()
        self.feed(p.Offer(txnode, self.node_id))
        self.drain()
        assert p.Request(p.CLAIM, txnode, self.node_id) in self.mgmt()
        self.feed(p.Assign(txnode, self.node_id))
        assert self.node.txnode == txnode
        self.drain()

    def bind(self, channel: int, etag: int, uid: int) -> None:
        """Answer the channel's request (queued at the next tick) with Bind(etag, uid); it is
        relied on at once."""
        self.tick(1)
        self.feed(p.Bind(etag, uid))
        self.drain()
        assert self.node.channel_etag(channel) == etag


__all__ = ["CNodes", "CanEcb", "Wire", "c_nodes", "now_ms"]
