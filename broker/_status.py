"""A daemon's status on TCP: answers a StatusRequest frame with a Status frame (the TCP/IP
framing of ``docs/protocol.md``), so ``ups status`` and ``ups ls`` can ask it.

For the standalone CAN-ECB (``ups can-broker --status HOST:PORT``), which has no TCP face of
its own. It answers only status: every other frame ends the link. At most ``MAX_LINKS`` links
at once: a new one closes the oldest link that has not asked yet (``status_evicted``), or, when
every link has asked and waits for its answer, is closed itself (``status_refused_busy``). A
link that sends no request within ``READ_TIMEOUT`` seconds, or whose answer is not written
within ``ANSWER_TIMEOUT``, is closed (``status_timed_out``). So idle links cannot keep a real
request out, and whoever asks is answered within ``READ_TIMEOUT`` of connecting plus the
pacing. The Status is built at most once per ``STATUS_GAP`` seconds however many ask
(``StatusPacer``), and carries these counters in its ``stats``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from ups import _tcpwire as w
from ups._address import parse_address
from ups._errors import DecodeError
from ups._statuspacer import StatusPacer

log = logging.getLogger("ups.status")

MAX_LINKS = 16  #: status links open at once
READ_TIMEOUT = 2.0  #: seconds a link may take to ask
ANSWER_TIMEOUT = 5.0  #: seconds an answer may take to be built and written
MAX_REQUEST = 1024  #: bytes: a StatusRequest is a few
_LOG_GAP = 1.0  # seconds between two logs of links turned away


class _StatusLink:
    __slots__ = ("asked", "evicted", "writer")

    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.asked = False  # it sent its StatusRequest: it is not idle
        self.evicted = False  # closed to make room for a newer link


class StatusServer:
    """Serves ``info()`` to whoever asks, on ``address``; ``counters`` (``status_...``) are
    added to the ``stats`` of what it serves."""

    def __init__(self, address: str, info: Callable[[], dict[str, Any]]) -> None:
        self.host, self.port = parse_address(address)
        self._info = info
        self._server: asyncio.Server | None = None
        self._links: dict[asyncio.Task[None], _StatusLink] = {}  # oldest first
        self.counters = dict.fromkeys(
            ("status_refused_busy", "status_evicted", "status_timed_out", "status_bad_requests"),
            0,
        )
        self._pacer = StatusPacer(self._served, self.counters, who="the status port")
        self._logged_at = float("-inf")

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("status on %s:%d", self.host, self.port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
        for link in self._links.values():  # their reads end; cancelling them would log
            link.writer.close()
        self._pacer.close()  # answers still awaited end too
        await asyncio.gather(*self._links, return_exceptions=True)

    def _served(self) -> dict[str, Any]:
        info = self._info()
        return {**info, "stats": {**info.get("stats", {}), **self.counters}}

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        if len(self._links) >= MAX_LINKS and not self._make_room():
            self._turned_away("status_refused_busy")
            writer.close()
            return
        link = self._links[task] = _StatusLink(writer)
        try:
            decoder = w.Decoder(max_frame=MAX_REQUEST)
            async with asyncio.timeout(READ_TIMEOUT):
                while not link.asked and (data := await reader.read(MAX_REQUEST)):
                    frames = decoder.feed(data)
                    if any(not isinstance(f, w.StatusRequest) for f in frames):
                        self.counters["status_bad_requests"] += 1
                        return
                    link.asked = bool(frames)
            if not link.asked:  # closed without asking (or evicted)
                return
            async with asyncio.timeout(ANSWER_TIMEOUT):
                writer.write(await self._pacer.next_frame())
                await writer.drain()
                self.counters["status_answers"] += 1
        except TimeoutError:
            self._turned_away("status_timed_out")
        except (DecodeError, ConnectionError):
            if not link.evicted:
                self.counters["status_bad_requests"] += 1
        except Exception:  # a bug in info(): logged (by the pacer), the daemon serves on
            self.counters["status_bad_requests"] += 1
        finally:
            self._links.pop(task, None)
            writer.close()

    def _make_room(self) -> bool:
        """Close the oldest link that has not asked yet; False if every link has asked."""
        for task, link in self._links.items():
            if not link.asked:
                del self._links[task]
                link.evicted = True
                link.writer.transport.abort()  # its read ends: its task returns
                self._turned_away("status_evicted")
                return True
        return False

    def _turned_away(self, counter: str) -> None:
        """Count a link closed by a bound; log the counts at most once a second."""
        self.counters[counter] += 1
        now = time.monotonic()
        if now - self._logged_at >= _LOG_GAP:
            self._logged_at = now
            log.warning(
                "status port: closed links that did not ask (%d idle past the %d at once, %d "
                "after %g s), refused %d while all %d waited for answers",
                self.counters["status_evicted"], MAX_LINKS, self.counters["status_timed_out"],
                READ_TIMEOUT, self.counters["status_refused_busy"], MAX_LINKS,
            )  # fmt: skip
