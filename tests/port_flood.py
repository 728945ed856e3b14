"""Attackers of a daemon's read-only port (the CAN-ECB's ``--status``, any ``--metrics``): links
that ask and reconnect at once, links that never ask, and links that trickle a byte a second.

Every attacker comes back as soon as the daemon closes its link, and all of them stop by
themselves: at ``stop()``, or ``limit`` seconds after they started, whichever comes first.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from ups import _tcpwire as w

#: a StatusRequest, and a frame header that announces 1000 bytes of a body that never comes
STATUS_REQUEST = w.encode(w.StatusRequest())
STATUS_TRICKLE = (w.VERSION << 24 | 1000).to_bytes(4, "big")
#: a scrape as Prometheus sends it, and a request whose headers never end
HTTP_REQUEST = b"GET /metrics HTTP/1.1\r\nHost: ups\r\nAccept: */*\r\n\r\n"
HTTP_TRICKLE = b"GET /metrics HTTP/1.1\r\nHost: ups\r\nX-Slow: "

_Kind = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


@dataclass
class Counts:
    """What the attackers did: links opened, requests sent, answers read to their end."""

    links: int = 0
    asked: int = 0
    answered: int = 0
    trickled: int = 0  # bytes trickled
    errors: dict[str, int] = field(default_factory=dict)


class Flood:
    """``askers`` links that send ``request``, read until the daemon closes, and reconnect at
    once; ``idle`` links that send nothing; ``tricklers`` that send ``trickle`` and then one
    more byte a second. Each reconnects as soon as its link is closed. ``start()`` them in a
    running loop (or ``async with``); they stop at ``stop()`` or after ``limit`` seconds."""

    def __init__(
        self,
        host: str,
        port: int,
        request: bytes,
        trickle: bytes,
        *,
        askers: int = 16,
        idle: int = 8,
        tricklers: int = 8,
        limit: float = 120.0,
    ) -> None:
        self.host, self.port = host, port
        self.request, self.trickle = request, trickle
        self.sizes = (askers, idle, tricklers)
        self.limit = limit
        self.counts = Counts()
        self._tasks: list[asyncio.Task[None]] = []

    def start(self) -> None:
        askers, idle, tricklers = self.sizes
        kinds = [self._ask] * askers + [self._idle] * idle + [self._trickle] * tricklers
        self._tasks = [asyncio.create_task(self._bounded(kind)) for kind in kinds]

    async def stop(self) -> Counts:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        return self.counts

    async def __aenter__(self) -> Flood:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def _bounded(self, kind: _Kind) -> None:
        """Run one attacker, link after link, for ``limit`` seconds at most."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.limit):
                while True:
                    await self._link(kind)

    async def _link(self, kind: _Kind) -> None:
        try:
            reader, writer = await asyncio.open_connection(self.host, self.port)
        except OSError as exc:
            self._error(exc)
            await asyncio.sleep(0)  # the next try comes after the other attackers' turns
            return
        self.counts.links += 1
        try:
            await kind(reader, writer)
        except OSError as exc:  # reset by the daemon: a link as any other
            self._error(exc)
        finally:
            writer.close()

    def _error(self, exc: OSError) -> None:
        name = type(exc).__name__
        self.counts.errors[name] = self.counts.errors.get(name, 0) + 1

    async def _ask(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(self.request)
        self.counts.asked += 1
        got = 0
        while data := await reader.read(1 << 16):
            got += len(data)
        self.counts.answered += got > 0

    async def _idle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read()  # until the daemon closes it

    async def _trickle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(self.trickle)
        closed = asyncio.create_task(reader.read())
        try:
            while not closed.done():
                await asyncio.wait({closed}, timeout=1.0)  # a byte a second, until closed
                if not closed.done():
                    writer.write(b"a")
                    await writer.drain()
                    self.counts.trickled += 1
        finally:
            closed.cancel()
            await asyncio.gather(closed, return_exceptions=True)
