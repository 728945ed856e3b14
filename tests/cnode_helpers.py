"""The C node (libups through ``ups._cnode``) on a python-can virtual bus, for the tests."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field

import can

from ups._cnode import CNode, CNodeRunner, Event, now_ms
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


__all__ = ["CNodes", "CanEcb", "c_nodes", "now_ms"]
