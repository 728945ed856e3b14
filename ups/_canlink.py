"""One python-can bus feeding one asyncio loop, shared by every handler of a process.

Every node of one event loop whose bus spec names the same interface, channel and options
shares one link (``CanLink.shared``), and so does a CAN-ECB hosted beside them (the gateway):
a frame sent by one handler is handed to the others at once, as if they were separate nodes
on the bus, and the echo that some interfaces return for our own frames is dropped here. So
N nodes of a process cost one socket and one read per frame, not N.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import importlib
import inspect
import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can

from ._errors import ConfigError

log = logging.getLogger(__name__)

#: Interfaces that hand every sent frame back to the sender.
_ECHOING_INTERFACES = frozenset({"udp_multicast"})
_RX_BATCH = 256  # frames read per wake-up before yielding to the loop
_ECHO_WINDOW = 4096  # sent frames remembered while their echo is awaited
_ECHO_LOOKAHEAD = 8  # echoes may be this many places out of order (or lost)
_RCVBUF = 4 << 20
MAX_BACKLOG = 16384  #: frames of transfers waiting for room in the interface (past it: refused)
BACKLOG_TIMEOUT = 2.0  #: seconds without the interface taking a frame before the backlog goes
_RETRY_FIRST, _RETRY_MAX = 0.0005, 0.01  # seconds between tries while the interface is full

Frame = can.Message
Handler = Callable[[can.Message], None]
Accepts = Callable[[can.Message], bool]

#: (event loop, bus key) -> the link its nodes share (see ``CanLink.shared``)
_shared: dict[tuple[asyncio.AbstractEventLoop, tuple[Any, ...]], CanLink] = {}
_shared_lock = threading.Lock()


def parse_bus_spec(spec: str) -> dict[str, Any]:
    """Parse ``INTERFACE:CHANNEL[,key=value...]`` into python-can ``Bus`` keyword arguments.

    Values that read as integers (``500000``, ``0x10``), floats or ``true``/``false`` are
    converted; everything else stays a string.
    """
    head, *pairs = spec.split(",")
    interface, sep, channel = head.partition(":")
    if not sep or not interface or not channel:
        raise ConfigError(f"bad CAN bus {spec!r}: expected INTERFACE:CHANNEL[,key=value...]")
    kwargs: dict[str, Any] = {"interface": interface, "channel": channel}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ConfigError(f"bad CAN bus option {pair!r} in {spec!r}: expected key=value")
        kwargs[key.strip()] = _option_value(value.strip())
    return kwargs


def _option_value(text: str) -> Any:
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for convert in (lambda t: int(t, 0), float):
        try:
            return convert(text)
        except ValueError:
            pass
    return text


#: options python-can takes for any interface (it ignores them where they mean nothing)
_COMMON_OPTIONS = frozenset({"bitrate", "data_bitrate", "fd", "timing", "receive_own_messages"})


def _check_options(kwargs: dict[str, Any]) -> None:
    """An option the interface's bus class does not name is a typo: python-can would pass it
    on unused, silently. Interfaces that cannot be loaded here are left to python-can."""
    entry = can.interfaces.BACKENDS.get(kwargs["interface"])
    if entry is None:
        return
    try:
        bus_class = getattr(importlib.import_module(entry[0]), entry[1])
        params = inspect.signature(bus_class.__init__).parameters
    except Exception:  # a missing vendor library, or no signature: python-can will say
        return
    known = {n for n, p in params.items() if p.kind is not p.VAR_KEYWORD} | _COMMON_OPTIONS
    for key in kwargs.keys() - known - {"interface", "self"}:
        takes = ", ".join(sorted(known - {"self", "channel"}))
        raise ConfigError(
            f"unknown option {key!r} for the {kwargs['interface']} interface (it takes: {takes})"
        )


def check_bus_spec(spec: str) -> dict[str, Any]:
    """``parse_bus_spec``, and the options checked against the interface's (a typo is an
    error, not an option python-can passes on unused)."""
    kwargs = parse_bus_spec(spec)
    _check_options(kwargs)
    return kwargs


def open_bus(spec: str) -> can.BusABC:
    """Open the python-can bus named by ``spec`` (see ``parse_bus_spec``)."""
    kwargs = check_bus_spec(spec)
    try:
        bus = can.Bus(**kwargs)
    except OSError as exc:
        if exc.errno == errno.EAFNOSUPPORT and kwargs.get("interface") == "socketcan":
            raise ConfigError(
                f"cannot open CAN bus {spec!r}: this kernel has no SocketCAN (address family "
                "not supported). In one process use --can virtual:NAME; across processes, "
                "--can udp_multicast:239.74.163.2,port=43114 inside scripts/netns-run"
            ) from exc
        raise ConfigError(f"cannot open CAN bus {spec!r}: {exc}") from exc
    except (can.CanError, ValueError, ImportError, TypeError) as exc:
        raise ConfigError(f"cannot open CAN bus {spec!r}: {exc}") from exc
    _widen_receive_buffer(bus)
    return bus


def _widen_receive_buffer(bus: can.BusABC) -> None:
    """The default 212 KB socket receive buffer (udp_multicast, SocketCAN) overflows on bursts
    of a few hundred frames, such as the transfers of a few 1 KiB events on a vcan, which has
    no bit rate to pace them. Beyond net.core.rmem_max only root may widen it (RCVBUFFORCE)."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None) or getattr(
        bus, "socket", None
    )
    if isinstance(sock, socket.socket):
        for option in (getattr(socket, "SO_RCVBUFFORCE", 33), socket.SO_RCVBUF):
            try:
                sock.setsockopt(socket.SOL_SOCKET, option, _RCVBUF)
                return
            except OSError:
                continue


class CanLink:
    """A bus, the loop that reads it, and the handlers each received frame is given to."""

    def __init__(
        self,
        bus: can.BusABC,
        *,
        owns_bus: bool = True,
        spec: str | None = None,
        fd: bool | None = None,
    ) -> None:
        self.bus = bus
        if fd is None:
            fd = getattr(bus, "protocol", None) in (
                can.CanProtocol.CAN_FD, can.CanProtocol.CAN_FD_NON_ISO
            )  # fmt: skip
        #: CAN FD: events larger than 8 bytes travel in 64-byte frames with bit-rate switching
        self.fd = bool(fd)
        self.mtu = 64 if self.fd else 8
        self._spec = spec
        self._owns_bus = owns_bus
        self._handlers: list[Handler] = []
        self._filters: dict[Handler, list[dict[str, Any]] | None] = {}
        #: each handler with the test of its filters (None: it takes every frame); used when
        #: the link has several handlers, which the bus filters only by their union
        self._routes: list[tuple[Handler, Accepts | None]] = []
        self._echoes = _interface_name(bus) in _ECHOING_INTERFACES
        self._awaiting_echo: deque[tuple[int, bytes]] = deque()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reader_fd = -1
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._closed = False
        self._backlog: deque[tuple[can.Message, Handler | None]] = deque()
        self._drainer: asyncio.Task[None] | None = None
        self.rx_frames = 0
        self.tx_frames = 0
        self.tx_failed = 0
        self.backlog_full = 0
        self.rx_errors = 0
        self.handler_errors = 0
        self._shared_key: tuple[asyncio.AbstractEventLoop, tuple[Any, ...]] | None = None
        self._users = 0

    def __str__(self) -> str:
        return self._spec or str(getattr(self.bus, "channel_info", "a CAN bus"))

    def stats(self) -> dict[str, int]:
        """Frames read and sent, and what went wrong, since the link opened."""
        return {
            "rx_frames": self.rx_frames,
            "tx_frames": self.tx_frames,
            "tx_failed": self.tx_failed,
            "backlog_full": self.backlog_full,
            "rx_errors": self.rx_errors,
            "handler_errors": self.handler_errors,
            "backlog": len(self._backlog),
        }

    @classmethod
    def open(cls, spec: str) -> CanLink:
        """Open the bus named by ``spec``; it is CAN FD when the spec says ``fd=True``."""
        fd = parse_bus_spec(spec).get("fd") is True
        return cls(open_bus(spec), owns_bus=True, spec=spec, fd=fd)

    @classmethod
    def shared(cls, spec: str) -> CanLink:
        """The link of the running event loop to the bus ``spec`` names: opened by its first
        user, then shared by every caller in this loop whose spec names the same interface,
        channel and options (in any order or spelling). Each user gives it back with
        ``release``; the last one closes it. A python-can bus object passed to a node, or a
        link from ``open``, is a connection of its own."""
        kwargs = parse_bus_spec(spec)
        key = (asyncio.get_running_loop(), tuple(sorted((k, repr(v)) for k, v in kwargs.items())))
        with _shared_lock:
            link = _shared.get(key)
            if link is None or link._closed:
                link = cls.open(spec)
                link._shared_key = key
                _shared[key] = link
            link._users += 1
        return link

    def release(self) -> None:
        """A user of a shared link is done with it: the last one closes it. On a link that is
        not shared, the same as ``close``."""
        key = self._shared_key
        if key is None:
            self.close()
            return
        with _shared_lock:
            self._users -= 1
            if self._users > 0:
                return
            if _shared.get(key) is self:
                del _shared[key]
        self.close()

    @property
    def channel_info(self) -> str:
        """The bus's own description, or the spec it was opened with when it has none."""
        info = str(getattr(self.bus, "channel_info", "unknown"))
        return self._spec if info == "unknown" and self._spec else info

    def add_handler(self, handler: Handler, filters: list[dict[str, Any]] | None = None) -> None:
        """Give every received frame to ``handler``; ``filters`` says which frames it needs."""
        self._handlers.append(handler)
        self.set_filters(handler, filters)

    def remove_handler(self, handler: Handler) -> None:
        with contextlib.suppress(ValueError):
            self._handlers.remove(handler)
        self._filters.pop(handler, None)
        self._route()

    def set_filters(self, handler: Handler, filters: list[dict[str, Any]] | None) -> None:
        """Declare the frames ``handler`` needs, as python-can ``can_filters`` (None: all).

        The bus gets the union of every handler's filters: applied in the kernel on SocketCAN,
        in python-can for other interfaces. When the link has several handlers, each is also
        handed only the frames its own filters accept, as if it had a bus of its own.
        """
        self._filters[handler] = filters
        self._route()
        union: list[dict[str, Any]] | None = []
        for wanted in self._filters.values():
            if wanted is None:
                union = None
                break
            assert union is not None
            union.extend(wanted)
        self.bus.set_filters(union)  # type: ignore[arg-type]

    def _route(self) -> None:
        self._routes = [(h, _accepts(self._filters.get(h))) for h in self._handlers]

    def start(self) -> None:
        """Start reading the bus into the running loop."""
        if self._loop is not None:
            return
        self._loop = asyncio.get_running_loop()
        try:
            fd = self.bus.fileno()
        except (NotImplementedError, OSError):
            fd = -1
        if fd >= 0:
            self._reader_fd = fd
            self._loop.add_reader(fd, self._on_readable)
        else:
            self._thread = threading.Thread(target=self._rx_thread, name="ups-can-rx", daemon=True)
            self._thread.start()

    def send(
        self, can_id: int, data: bytes, origin: Handler | None = None, fd: bool = False
    ) -> bool:
        """Send an extended frame now (a CAN FD frame with bit-rate switching if ``fd``); hand
        it to the local handlers other than ``origin``.

        Never blocks: when the interface cannot take the frame (its transmit queue is full or
        the bus is off), the frame is dropped, counted in ``tx_failed`` and False is returned.
        While frames of a transfer wait in the backlog, the frame waits behind them instead.
        """
        frame = can.Message(
            arbitration_id=can_id, data=data, is_extended_id=True, is_fd=fd, bitrate_switch=fd
        )
        if self._backlog:
            return self._queue([frame], origin)
        if self._offer(frame, origin):
            return True
        self._failed(1, "CAN send failed")
        return False

    def send_transfer(
        self, can_id: int, frames: list[bytes], origin: Handler | None = None, fd: bool = False
    ) -> bool:
        """Send the frames of one transfer, in order and none left out: what the interface
        cannot take now waits in the backlog (``MAX_BACKLOG`` frames) and goes as it makes
        room. Returns False, sending none of them, when the backlog has no room for them all."""
        messages = [
            can.Message(
                arbitration_id=can_id, data=d, is_extended_id=True, is_fd=fd, bitrate_switch=fd
            )
            for d in frames
        ]
        if not self._backlog:
            for i, frame in enumerate(messages):
                if not self._offer(frame, origin):
                    return self._queue(messages[i:], origin)
            return True
        return self._queue(messages, origin)

    def _offer(self, frame: can.Message, origin: Handler | None) -> bool:
        try:
            self.bus.send(frame, timeout=0)
        except (can.CanError, OSError):
            return False
        self.tx_frames += 1
        if self._echoes:
            self._awaiting_echo.append((frame.arbitration_id, bytes(frame.data)))
            if len(self._awaiting_echo) > _ECHO_WINDOW:
                self._awaiting_echo.popleft()
        frame.timestamp = time.time()
        for handler, accepts in self._routes:
            if handler is not origin and (accepts is None or accepts(frame)):
                handler(frame)
        return True

    def _queue(self, frames: list[can.Message], origin: Handler | None) -> bool:
        if len(self._backlog) + len(frames) > MAX_BACKLOG or self._loop is None:
            self.backlog_full += 1  # (a transfer cut short is broken: its receivers count it)
            self._failed(len(frames), "CAN backlog full: frames dropped")
            return False
        self._backlog.extend((frame, origin) for frame in frames)
        if self._drainer is None or self._drainer.done():
            self._drainer = self._loop.create_task(self._drain())
        return True

    async def _drain(self) -> None:
        """Hand the backlog to the interface as it makes room; give it up when the interface
        takes nothing for ``BACKLOG_TIMEOUT`` s (the bus is off, or nobody acknowledges)."""
        backlog = self._backlog
        delay = _RETRY_FIRST
        stuck_since = time.monotonic()
        while backlog:
            frame, origin = backlog[0]
            if self._offer(frame, origin):
                backlog.popleft()
                delay = _RETRY_FIRST
                stuck_since = time.monotonic()
                continue
            if time.monotonic() - stuck_since > BACKLOG_TIMEOUT:
                self._failed(len(backlog), "CAN interface takes no frames: backlog dropped")
                backlog.clear()
                return
            await asyncio.sleep(delay)
            delay = min(delay * 2, _RETRY_MAX)

    async def flush(self, timeout: float = BACKLOG_TIMEOUT) -> None:
        """Wait (at most ``timeout`` s) until the backlog has gone to the interface."""
        drainer = self._drainer
        if drainer is not None and not drainer.done():
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(drainer), timeout)

    def _failed(self, frames: int, what: str) -> None:
        before = self.tx_failed
        self.tx_failed += frames
        marks = any(before < mark <= self.tx_failed for mark in (1, 10, 100))
        if marks or before // 1000 != self.tx_failed // 1000:
            log.warning("%s (%d frames so far)", what, self.tx_failed)

    def _dispatch(self, frame: can.Message) -> None:
        self.rx_frames += 1
        if self._awaiting_echo and frame.is_extended_id and self._is_echo(frame):
            return
        routes = self._routes
        for handler, accepts in routes:
            if accepts is not None and len(routes) > 1 and not accepts(frame):
                continue  # the bus let it through for another handler of this link
            try:
                handler(frame)
            except Exception:  # a bug in one handler must not starve the others
                self.handler_errors += 1
                log.exception("CAN frame handler failed on %s", frame)

    def _is_echo(self, frame: can.Message) -> bool:
        key = (frame.arbitration_id, bytes(frame.data))
        waiting = self._awaiting_echo
        for i in range(min(_ECHO_LOOKAHEAD, len(waiting))):
            if waiting[i] == key:
                for _ in range(i + 1):  # echoes before it were lost: forget them
                    waiting.popleft()
                return True
        return False

    def _on_readable(self) -> None:
        recv = self.bus.recv
        for _ in range(_RX_BATCH):
            try:
                frame = recv(0)
            except (can.CanError, OSError) as exc:
                self._rx_error(exc)
                return
            if frame is None:
                return
            self._dispatch(frame)

    def _rx_thread(self) -> None:
        loop = self._loop
        assert loop is not None
        while not self._stopping.is_set():
            try:
                frame = self.bus.recv(0.05)
            except (can.CanError, OSError) as exc:
                if self._stopping.is_set():
                    return
                loop.call_soon_threadsafe(self._rx_error, exc)
                self._stopping.wait(0.1)
                continue
            if frame is not None:
                try:
                    loop.call_soon_threadsafe(self._dispatch, frame)
                except RuntimeError:  # the loop closed under us
                    return

    def _rx_error(self, exc: BaseException) -> None:
        self.rx_errors += 1
        if self.rx_errors in (1, 10, 100) or self.rx_errors % 1000 == 0:
            log.warning("CAN receive error (%d so far): %s", self.rx_errors, exc)

    def close(self) -> None:
        """Stop reading and, if this link opened the bus, shut it down. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._stopping.set()
        if self._drainer is not None:
            self._drainer.cancel()
        self._backlog.clear()
        if self._reader_fd >= 0 and self._loop is not None and not self._loop.is_closed():
            self._loop.remove_reader(self._reader_fd)
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        self._handlers.clear()
        self._routes = []
        if self._owns_bus:
            self.bus.shutdown()


def _accepts(filters: list[dict[str, Any]] | None) -> Accepts | None:
    """The test python-can applies for ``filters`` (None: every frame passes)."""
    if filters is None:
        return None
    rules = [(f["can_id"] & f["can_mask"], f["can_mask"], f.get("extended")) for f in filters]

    def accepts(frame: can.Message) -> bool:
        can_id, extended = frame.arbitration_id, frame.is_extended_id
        return any(
            can_id & mask == want and (ext is None or ext == extended) for want, mask, ext in rules
        )

    return accepts


def _interface_name(bus: can.BusABC) -> str:
    module = type(bus).__module__  # e.g. can.interfaces.udp_multicast.bus
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[:2] == ["can", "interfaces"] else module
