"""A daemon's status on TCP: answers a StatusRequest frame with a Status frame (the TCP/IP
framing of ``docs/protocol.md``), so ``ups status`` and ``ups ls`` can ask it.

For the standalone CAN-ECB (``ups can-broker --status HOST:PORT``), which has no TCP face of
its own. It answers only status: every other frame ends the link. At most ``MAX_LINKS`` links
at once (more are closed at once, counted); a link that sends no request within
``READ_TIMEOUT`` seconds is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

from ups import _tcpwire as w
from ups._address import parse_address
from ups._errors import DecodeError

log = logging.getLogger("ups.status")

MAX_LINKS = 16  #: status links open at once
READ_TIMEOUT = 5.0  #: seconds a link may take to ask
MAX_REQUEST = 1024  #: bytes: a StatusRequest is a few


class StatusServer:
    """Serves ``info()`` to whoever asks, on ``address``."""

    def __init__(self, address: str, info: Callable[[], dict[str, Any]]) -> None:
        self.host, self.port = parse_address(address)
        self._info = info
        self._server: asyncio.Server | None = None
        self._links: dict[asyncio.Task[None], asyncio.StreamWriter] = {}
        self.counters = {"answered": 0, "refused_busy": 0, "bad_requests": 0}

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("status on %s:%d", self.host, self.port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
        for writer in self._links.values():  # their reads end; cancelling them would log
            writer.close()
        await asyncio.gather(*self._links, return_exceptions=True)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        if len(self._links) >= MAX_LINKS:
            self.counters["refused_busy"] += 1
            writer.close()
            return
        self._links[task] = writer
        try:
            decoder = w.Decoder(max_frame=MAX_REQUEST)
            async with asyncio.timeout(READ_TIMEOUT):
                while data := await reader.read(MAX_REQUEST):
                    frames = decoder.feed(data)
                    if any(not isinstance(f, w.StatusRequest) for f in frames):
                        self.counters["bad_requests"] += 1
                        return
                    if frames:
                        writer.write(w.encode(w.Status(self._info())))
                        await writer.drain()
                        self.counters["answered"] += 1
                        return
        except (DecodeError, TimeoutError, ConnectionError):
            self.counters["bad_requests"] += 1
        except Exception:  # a bug in info(): logged, counted, the daemon serves on
            self.counters["bad_requests"] += 1
            log.exception("could not answer a status request")
        finally:
            self._links.pop(task, None)
            writer.close()
