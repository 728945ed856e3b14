"""What keeps ``ups console``'s web server to its own page and its own users: which Host
names it answers (DNS rebinding), how long a request may take to arrive, how far behind a
live stream's reader may fall. Each refusal is counted and logged (``Notes``).

- **Host names.** A page a browser loaded from ``http://attacker.example:8470`` may read and
  post whatever that name's server answers; the attacker then points the name at the
  console's address (DNS rebinding), and the browser sends ``Host: attacker.example:8470``.
  So a request is served only when its Host is an address (no page can be served *under* an
  IP address but that address's own), or a name on the allow-list (``--allow-host``; by
  default ``localhost`` and the ``--listen`` host when it is a name). The port is not
  compared: a tunnel or a forwarded port keeps working.
- **Slow requests.** A connection must deliver a whole request (line and headers; a POST's
  body in the handler, within the same time) within ``HEADER_TIMEOUT`` seconds of opening, or
  of the end of its previous request; else it is closed (``slow_requests``; an idle
  keep-alive connection too).
- **Streams that stop reading** (``backlog``): bytes written that the client's TCP has not
  acknowledged, and those not yet handed to the kernel. A reader that keeps up leaves about
  none; one that stopped leaves its snapshots piling up once its receive buffer is full.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # asyncio is not loaded for ``ups --help``
    import asyncio

log = logging.getLogger("ups.console")

HEADER_TIMEOUT = 10.0  #: seconds a connection has to deliver a whole request
NOTE_EVERY = 10.0  #: seconds between two log lines of one kind of refusal (all are counted)


class Notes:
    """Counts a refusal and logs it, at most once per ``every`` seconds for each counter (a
    flood of them must not flood the log); the line says how many there were so far."""

    def __init__(self, counters: dict[str, int], every: float = NOTE_EVERY) -> None:
        self.counters, self.every = counters, every
        self._said: dict[str, float] = {}

    def __call__(self, counter: str, text: str, *args: object) -> None:
        self.counters[counter] = self.counters.get(counter, 0) + 1
        now = time.monotonic()
        if now - self._said.get(counter, -math.inf) >= self.every:
            self._said[counter] = now
            log.warning(f"{text} ({counter}: %d so far)", *args, self.counters[counter])


# --- Host names ------------------------------------------------------------------------------


def host_name(host: str) -> str:
    """The name of a Host header, without its port and brackets, lower case, no final dot."""
    host = host.strip().lower()
    if host.startswith("["):  # [::1]:8470
        return host[1 : host.find("]")] if "]" in host else host
    if host.count(":") == 1:
        host = host.partition(":")[0]
    return host.rstrip(".")


def allowed_names(listen_host: str, given: list[str] | None) -> frozenset[str]:
    """The Host names served: ``localhost``, the listen host when it is a name, and the
    names given (``--allow-host``)."""
    names = {"localhost", *(host_name(n) for n in given or ())}
    if listen_host and not is_address(listen_host):
        names.add(host_name(listen_host))
    return frozenset(names)


def is_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name.partition("%")[0])
    except ValueError:
        return False
    return True


def host_allowed(host: str, names: frozenset[str]) -> bool:
    name = host_name(host)
    return is_address(name) or name in names


# --- slow requests ---------------------------------------------------------------------------


@dataclass
class _Connection:
    timer: asyncio.TimerHandle | None = None
    serving: int = 0  #: requests being handled now


@dataclass
class RequestClock:
    """Closes a connection that has not delivered a whole request within ``timeout`` seconds
    of opening or of its previous request's end. ``protocol_factory`` wraps aiohttp's server
    (one handler per connection); ``begin``/``end`` mark each request, from a middleware."""

    timeout: float
    notes: Notes
    _open: dict[Any, _Connection] = field(default_factory=dict)

    def protocol_factory(self, server: Any) -> Any:
        def factory() -> Any:
            handler = server()  # aiohttp's RequestHandler for this connection
            self._arm(handler, self._open.setdefault(handler, _Connection()))
            return handler

        return factory

    def begin(self, handler: Any) -> None:
        conn = self._open.setdefault(handler, _Connection())
        conn.serving += 1
        if conn.timer is not None:
            conn.timer.cancel()
            conn.timer = None

    def end(self, handler: Any) -> None:
        conn = self._open.get(handler)
        if conn is not None:
            conn.serving -= 1
            if conn.serving <= 0:
                self._arm(handler, conn)

    def _arm(self, handler: Any, conn: _Connection) -> None:
        import asyncio

        if conn.timer is not None:
            conn.timer.cancel()
        loop = asyncio.get_running_loop()
        conn.timer = loop.call_later(self.timeout, self._expired, handler)

    def _expired(self, handler: Any) -> None:
        conn = self._open.pop(handler, None)
        transport = getattr(handler, "transport", None)
        if conn is None or conn.serving > 0 or transport is None or transport.is_closing():
            return  # closed meanwhile: forgotten
        peer = transport.get_extra_info("peername") or ("?",)
        self.notes("slow_requests", "connection from %s closed: no whole request within %g s",
                   peer[0], self.timeout)  # fmt: skip
        handler.force_close()
        transport.close()

    def close(self) -> None:
        for conn in self._open.values():
            if conn.timer is not None:
                conn.timer.cancel()
        self._open.clear()


# --- streams that stop reading ---------------------------------------------------------------


def backlog(transport: Any) -> int | None:
    """Bytes written to ``transport`` that its peer's TCP has not acknowledged (Linux's
    SIOCOUTQ: unsent or unacknowledged in the kernel), with those still in the transport's
    own buffer; None where the kernel does not say."""
    sock = transport.get_extra_info("socket")
    if sock is None:
        return None
    try:
        import fcntl
        import struct
        import termios

        raw = fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
    except (ImportError, OSError, AttributeError):
        return None
    queued: int = struct.unpack("=i", raw)[0]
    with contextlib.suppress(Exception):
        queued += int(transport.get_write_buffer_size())
    return queued


def abort(transport: Any) -> None:
    """Let a reader that stopped reading go at once: a reset, not a FIN queued behind what it
    never read (which would hold the kernel's memory until TCP gives up)."""
    if transport is None:
        return
    sock = transport.get_extra_info("socket")
    if sock is not None:
        import socket
        import struct

        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    transport.abort()


__all__ = [
    "HEADER_TIMEOUT",
    "NOTE_EVERY",
    "Notes",
    "RequestClock",
    "abort",
    "allowed_names",
    "backlog",
    "host_allowed",
    "host_name",
    "is_address",
]
