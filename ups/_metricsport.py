"""The HTTP port of ``--metrics``: ``ups/_port.py``'s admission, in a thread of its own.

The port runs its own event loop in the thread ``ups-metrics``, so however the port is used,
the daemon's loop does no more than read its counters when a scrape asks (``_metrics.py``).
Each link sends one HTTP request and gets one answer from the WSGI app (prometheus-client's),
made by one of ``MAX_SCRAPES`` threads; then it is closed, as HTTP/1.0 servers do. The
admission (``LIMITS``) is the status port's: links that never send a whole request, trickle,
or do not read their answer give way after their turn to a newcomer, and links that scrape
and reconnect at once wait in line behind it.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import re
import socket
import threading
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple
from urllib.parse import unquote

from ._port import BadRequest, Limits, Port

MAX_SCRAPES = 8  #: answers made at once (threads); more links wait for one of them
#: at most 64 links at once, 64 in line; 2 s to send a whole request (8 KiB at most), 0.5 s
#: turn; 10 s for an answer to be made and written (twice the 5 s a scrape waits for the
#: daemon's loop, ``_metrics.SCRAPE_TIMEOUT``)
LIMITS = Limits(links=64, waiting=64, turn=0.5, read_timeout=2.0, answer_timeout=10.0,
                wait_timeout=5.0, max_request=8192)  # fmt: skip
PROMISE = 5.0  #: seconds: whoever scrapes is answered within this (docs/security.md)
_END = re.compile(rb"\r?\n\r?\n")  # the end of a request's head

App = Callable[[dict[str, Any], Callable[..., Any]], Iterable[bytes]]


class _Request(NamedTuple):
    method: str
    target: str
    headers: dict[str, str]  # by lower-case name


def _reply(status: str, text: str) -> bytes:
    return _response(status, [("Content-Type", "text/plain")], text.encode())


def _response(status: str, headers: list[tuple[str, str]], body: bytes) -> bytes:
    head = [f"HTTP/1.1 {status}", *(f"{k}: {v}" for k, v in headers)]
    head += [f"Content-Length: {len(body)}", "Connection: close", "", ""]
    return "\r\n".join(head).encode("latin-1") + body


def _request_reader() -> Callable[[bytes], _Request | None]:
    """A link's reader: the request once its head (request line and headers) is whole."""
    buf = bytearray()

    def feed(data: bytes) -> _Request | None:
        buf.extend(data)
        end = _END.search(buf)
        if end is None:
            if len(buf) >= LIMITS.max_request:
                raise BadRequest(_reply("431 Request Header Fields Too Large", "too large\n"))
            return None
        line, *fields = bytes(buf[: end.start()]).decode("latin-1").split("\n")
        parts = line.strip().split()
        if len(parts) != 3 or not parts[2].startswith("HTTP/"):
            raise BadRequest(_reply("400 Bad Request", "not an HTTP request\n"))
        headers = {}
        for field in fields:
            name, colon, value = field.partition(":")
            if not colon:
                raise BadRequest(_reply("400 Bad Request", "not an HTTP header\n"))
            headers[name.strip().lower()] = value.strip()
        return _Request(parts[0], parts[1], headers)

    return feed


def _respond(app: App, request: _Request) -> bytes:
    """``app``'s answer to ``request``, as the bytes of an HTTP response (in a worker)."""
    path, _, query = request.target.partition("?")
    environ = {
        "REQUEST_METHOD": request.method,
        "PATH_INFO": unquote(path),
        "QUERY_STRING": query,
        "SERVER_PROTOCOL": "HTTP/1.1",
        **{f"HTTP_{k.upper().replace('-', '_')}": v for k, v in request.headers.items()},
    }
    started: list[Any] = []

    def start_response(status: str, headers: list[tuple[str, str]], exc_info: Any = None) -> None:
        started[:] = [status, headers]

    body = b"".join(app(environ, start_response))
    status, headers = started
    return _response(status, headers, body)


class HttpPort:
    """Serves ``app`` on the bound socket ``sock`` from the thread ``ups-metrics``."""

    def __init__(self, sock: socket.socket, app: App) -> None:
        self._sock = sock
        self._app = app
        self._port: Port[_Request] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None

    @property
    def counters(self) -> dict[str, int]:
        """The admission's counters (``Port.counters``), zeros before it started."""
        port = self._port
        return dict(port.counters) if port else {}

    async def start(self) -> None:
        ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._thread = threading.Thread(target=self._run, args=(ready,), name="ups-metrics")
        self._thread.start()
        await asyncio.wrap_future(ready)

    async def close(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join)

    def _run(self, ready: concurrent.futures.Future[None]) -> None:
        try:
            asyncio.run(self._serve(ready))
        except BaseException as exc:  # before it served: start() raises it
            if not ready.done():
                ready.set_exception(exc)
            raise

    async def _serve(self, ready: concurrent.futures.Future[None]) -> None:
        loop = asyncio.get_running_loop()
        workers = concurrent.futures.ThreadPoolExecutor(MAX_SCRAPES, "ups-scrape")
        loop.set_default_executor(workers)  # asyncio.run waits for them at the end

        async def answer(request: _Request) -> bytes:
            return await loop.run_in_executor(None, _respond, self._app, request)

        port = Port("the metrics port", _request_reader, answer, LIMITS)
        await port.start(self._sock)
        self._port, self._loop, self._stop = port, loop, asyncio.Event()
        ready.set_result(None)
        try:
            await self._stop.wait()
        finally:
            await port.close()
