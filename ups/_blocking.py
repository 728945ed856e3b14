"""The node API for plain scripts: every call blocks; a private event loop runs in a thread."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

from ._channel import ChannelLike
from ._face import Overflow
from ._message import Message
from ._node import Node
from ._subscription import DEFAULT_QUEUE, Subscription

T = TypeVar("T")


class BlockingNode:
    """``Node`` for code without asyncio; takes the same arguments and joins at once::

    with BlockingNode(can="socketcan:vcan0") as node:
        sub = node.subscribe("robot/speed")
        node.publish("robot/speed", b"\\x10")
        print(sub.get_msg(timeout=1.0))
    """

    def __init__(self, **kwargs: Any) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="ups-blocking-loop", daemon=True
        )
        self._thread.start()
        self._node = Node(**kwargs)
        try:
            self._call(self._node.start())
        except BaseException:
            self._call(self._node.close())
            self._stop_loop()
            raise

    def _call(self, coro: Coroutine[Any, Any, T]) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result()

    def __enter__(self) -> BlockingNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def node(self) -> Node:
        """The asyncio node underneath (use it only from its own loop)."""
        return self._node

    def publish(
        self, channel: ChannelLike, data: bytes | bytearray | memoryview, *, wait: bool = False
    ) -> None:
        self._call(self._node.publish(channel, data, wait=wait))

    def declare(
        self,
        channel: ChannelLike,
        *,
        period_ms: float,
        deadline_ms: float,
        size_bytes: int = 8,
        jitter_ms: float = 0.0,
    ) -> int:
        """``Node.declare``: a real-time channel on CAN, admitted by the CAN-ECB or refused
        (``Unschedulable``); returns the priority it publishes with."""
        return self._call(
            self._node.declare(
                channel, period_ms=period_ms, deadline_ms=deadline_ms, size_bytes=size_bytes,
                jitter_ms=jitter_ms,
            )
        )  # fmt: skip

    def subscribe(
        self,
        *channels: ChannelLike,
        maxlen: int = DEFAULT_QUEUE,
        overflow: Overflow = "drop_oldest",
    ) -> BlockingSubscription:
        sub = self._call(self._node.subscribe(*channels, maxlen=maxlen, overflow=overflow))
        return BlockingSubscription(self, sub)

    def unsubscribe(self, target: BlockingSubscription | ChannelLike) -> None:
        inner = target._sub if isinstance(target, BlockingSubscription) else target
        self._call(self._node.unsubscribe(inner))

    def get_msg(self, timeout: float | None = None) -> Message:
        return self._call(self._node.get_msg(timeout))

    def set_priority(self, channel: ChannelLike, priority: int) -> None:
        self._call(_in_loop(self._node.set_priority, channel, priority))

    def stats(self) -> dict[str, int]:
        return self._call(_in_loop(self._node.stats))

    def close(self) -> None:
        """Close the node and stop its loop thread. Safe to call twice."""
        if self._loop.is_closed():
            return
        self._call(self._node.close())
        self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()


async def _in_loop(fn: Callable[..., T], *args: Any) -> T:
    """Run a plain method of the node inside its loop, where its state lives."""
    return fn(*args)


class BlockingSubscription:
    """A ``Subscription`` read with blocking calls; iterating ends when it is closed."""

    def __init__(self, owner: BlockingNode, sub: Subscription) -> None:
        self._owner = owner
        self._sub = sub

    @property
    def dropped(self) -> int:
        return self._sub.dropped

    def get_msg(self, timeout: float | None = None) -> Message:
        return self._owner._call(self._sub.get_msg(timeout))

    def __iter__(self) -> Iterator[Message]:
        return self

    def __next__(self) -> Message:
        try:
            return self._owner._call(self._sub.__anext__())
        except StopAsyncIteration:
            raise StopIteration from None

    def close(self) -> None:
        self._owner.unsubscribe(self)
