"""A subscription: the events of one or more channels, queued for one consumer or handed to
its callback as they arrive."""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable

from ._channel import Channel
from ._errors import Closed, ConfigError
from ._face import Overflow
from ._message import Message

log = logging.getLogger("ups")

DEFAULT_QUEUE = 1024
_LOG_GAP = 1.0  # seconds between two warnings about failing callbacks of one subscription
#: ``get_msg`` gives the event loop a turn every this many events, even when events are queued:
#: a consumer draining a deep queue must not starve the node's own heartbeats and reads
YIELD_EVERY = 64


class Subscription:
    """The events of one or more channels, queued for one consumer.

    The queue holds at most ``maxlen`` events. When it is full, ``overflow`` decides:
    ``"drop_oldest"`` (the default: the freshest data wins, as a control loop wants) discards the
    oldest queued event, ``"drop_newest"`` discards the arriving one. Either way ``dropped``
    counts it. Iterate with ``async for``; iteration ends when the subscription or node closes.

    A subscription made with a ``callback`` queues nothing: each event is handed to the callback
    as it arrives, in the event loop's thread, with no task switch (``get_msg`` is not for it).
    An exception the callback raises is logged and counted (``errors``); the next event comes
    all the same.

    ``patterns`` are the globs it was made with (``subscribe("robot/*")``); ``channels`` holds
    its channels, those the globs matched included, and grows as the network names more. Each
    message says its channel.

    ``unsubscribe`` is what ``close`` awaits: the node's ``unsubscribe``, which made it.
    """

    def __init__(
        self,
        unsubscribe: Callable[[Subscription], Awaitable[None]],
        channels: tuple[Channel, ...],
        maxlen: int,
        overflow: Overflow,
        callback: Callable[[Message], object] | None = None,
        patterns: tuple[str, ...] = (),
    ) -> None:
        self.channels = channels
        self.patterns = patterns
        self.maxlen = maxlen
        self.overflow: Overflow = overflow
        self.callback = callback
        self.dropped = 0
        self.errors = 0
        self._logged = -_LOG_GAP
        self._unsubscribe = unsubscribe
        self._queue: collections.deque[Message] = collections.deque()
        self._loop = asyncio.get_running_loop()
        self._waiter: asyncio.Future[None] | None = None
        self._closed = False
        self._served = 0

    def __repr__(self) -> str:
        names = ", ".join([*self.patterns, *(str(c) for c in self.channels)])
        return f"<Subscription [{names}] queued={len(self._queue)} dropped={self.dropped}>"

    @property
    def pending(self) -> int:
        """Events queued and not yet taken."""
        return len(self._queue)

    def _push(self, msg: Message) -> None:
        callback = self.callback
        if callback is not None:  # handed over as it arrives, in this very call
            try:
                callback(msg)
            except Exception:
                self._failed()
            return
        queue = self._queue
        if len(queue) >= self.maxlen:
            self.dropped += 1
            if self.overflow == "drop_newest":
                return
            queue.popleft()
        queue.append(msg)
        waiter = self._waiter
        if waiter is not None:
            self._waiter = None
            if not waiter.done():
                waiter.set_result(None)

    def _failed(self) -> None:
        """The callback raised (call it from the ``except``): count it, log now and then."""
        self.errors += 1
        now = time.monotonic()
        if now - self._logged >= _LOG_GAP:
            self._logged = now
            log.exception("the callback of %r failed (%d so far)", self, self.errors)

    async def get_msg(self, timeout: float | None = None) -> Message:
        """The next event; raises ``TimeoutError`` after ``timeout`` s, ``Closed`` once closed."""
        if self.callback is not None:
            raise ConfigError("this subscription hands its events to its callback")
        self._served += 1
        if self._served >= YIELD_EVERY:  # draining a deep queue still lets the loop run
            self._served = 0
            await asyncio.sleep(0)
        while not self._queue:
            if self._closed:
                raise Closed("subscription closed")
            waiter = self._loop.create_future()
            self._waiter = waiter
            try:
                if timeout is None:
                    await waiter  # the common case, without _wait's coroutine
                else:
                    await wait(self._loop, waiter, timeout)
            finally:
                self._waiter = None
        return self._queue.popleft()

    def __aiter__(self) -> AsyncIterator[Message]:
        return self

    async def __anext__(self) -> Message:
        try:
            return await self.get_msg()
        except Closed:
            raise StopAsyncIteration from None

    async def close(self) -> None:
        """Unsubscribe. Events already queued can still be taken."""
        await self._unsubscribe(self)

    def _close(self) -> None:
        self._closed = True
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)


async def wait(
    loop: asyncio.AbstractEventLoop, waiter: asyncio.Future[None], timeout: float | None
) -> None:
    """Await ``waiter``; raise ``TimeoutError`` after ``timeout`` s (cheaper than wait_for)."""
    if timeout is None:
        await waiter
        return
    timer = loop.call_later(timeout, _expire, waiter)
    try:
        await waiter
    finally:
        timer.cancel()


def _expire(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_exception(TimeoutError())
