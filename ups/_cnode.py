"""libups, the C node of ``c/``, from Python: its ctypes binding and a runner on a python-can bus.

``CNode`` wraps one ``ups_node_t`` of the compiled library (``c/build/libups.so``: the full
configuration, with transfers and CAN FD; ``libups-min.so``, the minimal one; ``libups-asan.so``,
the full one with AddressSanitizer and UndefinedBehaviorSanitizer). Each method is one call of
``c/ups.h``. ``CNodeRunner`` is the application loop a microcontroller would run: it feeds every
received frame to its nodes, ticks them every millisecond and sends what they queue, on any
python-can bus. ``ups c-node`` and the tests use these; no broker or gateway code is imported.

The library is built on first use with ``make -C c`` (a C compiler and make are needed).
"""

from __future__ import annotations

import asyncio
import ctypes
import fcntl
import subprocess
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from ._errors import ConfigError

C_DIR = Path(__file__).resolve().parent.parent / "c"
VARIANTS = {"full": "libups.so", "min": "libups-min.so", "asan": "libups-asan.so"}
SOURCES = ("ups.h", "ups_util.h", "ups_join.h", "ups_bind.h", "ups_transfer.h",
           "ups.c", "ups_join.c", "ups_bind.c", "ups_transfer.c", "ups_util.c",
           "host/ups_host.c", "Makefile")  # fmt: skip

# ups.h's constants (the header is the reference; tests check these against it)
FRAME_EXT, FRAME_FD, FRAME_BRS, FRAME_RTR, FRAME_ERR = 0x01, 0x02, 0x04, 0x08, 0x10
NOTE_JOINED, NOTE_JOIN_FAILED, NOTE_FILTERS, NOTE_CHANNELS, NOTE_DECLARATIONS = 1, 2, 4, 8, 16
FREE, WAITING, READY = 0, 1, 2
ERRORS = {
    -1: "ARGUMENT", -2: "FULL", -3: "UNBOUND", -4: "TOO_LARGE", -5: "BUSY", -6: "NOT_JOINED",
    -7: "TIMEOUT", -8: "TXNODES_FULL", -9: "ETAGS_FULL", -10: "LIMIT", -11: "FAILED",
    -12: "REFUSED",
}  # fmt: skip
COUNTERS = (
    "foreign", "malformed", "unknown", "filtered", "own_echo", "unbound_dropped", "tx_dropped",
    "rebinds", "moves", "large_lost",
)  # fmt: skip
_CONFIG = ("channels", "tx_depth", "transfers", "fd", "max_event", "rx_transfers",
           "declarations", "heard_binds", "counter_bytes", "mtu")  # fmt: skip


def build(
    variant: str = "full",
    *,
    targets: Mapping[str, str] = VARIANTS,
    sources: Sequence[str] = SOURCES,
    c_dir: Path | None = None,
) -> Path:
    """The compiled library of ``variant``, built (``make -C c``) if missing or older than its
    sources. Concurrent callers wait for one build (a lock file). ``targets`` (variant -> file
    under ``c/build``) and ``sources`` (what it is built from) name another library of ``c/``
    (libups-ecb: ``ups.broker.c_ecb``); ``c_dir``, another copy of ``c/``."""
    c_dir = C_DIR if c_dir is None else c_dir
    if variant not in targets:
        raise ConfigError(f"no variant {variant!r} (there are: {', '.join(targets)})")
    name = targets[variant]
    target = c_dir / "build" / name
    if not all((c_dir / s).exists() for s in sources):
        raise ConfigError(f"the C sources are not here ({c_dir}): {name} is built from a checkout")
    (c_dir / "build").mkdir(exist_ok=True)
    with open(c_dir / "build" / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        newest = max((c_dir / s).stat().st_mtime for s in sources)
        if not target.exists() or target.stat().st_mtime < newest:
            done = subprocess.run(
                # -B: stale by this check (the Makefile itself is a source, not make's)
                ["make", "-s", "-B", "-C", str(c_dir), f"build/{name}"],
                capture_output=True,
                text=True,
                check=False,
            )
            if done.returncode != 0:
                raise ConfigError(
                    f"could not build {target} (run 'make -C c lib' to see why):\n"
                    f"{done.stderr.strip()}"
                )
    return target


class _Frame(ctypes.Structure):
    _fields_ = [("id", ctypes.c_uint32), ("flags", ctypes.c_uint8), ("len", ctypes.c_uint8),
                ("data", ctypes.c_uint8 * 64)]  # fmt: skip


class _Event(ctypes.Structure):
    _fields_ = [("data", ctypes.POINTER(ctypes.c_uint8)), ("size", ctypes.c_uint16),
                ("channel", ctypes.c_uint8), ("priority", ctypes.c_uint8),
                ("txnode", ctypes.c_uint8)]  # fmt: skip


class _Filter(ctypes.Structure):
    _fields_ = [("id", ctypes.c_uint32), ("mask", ctypes.c_uint32)]


@dataclass(frozen=True, slots=True)
class Event:
    """One event the C node delivered."""

    channel: int  #: the index ups_subscribe() returned
    data: bytes
    priority: int
    txnode: int


_loaded: dict[Path, tuple[ctypes.CDLL, dict[str, int]]] = {}


def load(variant: str = "full") -> tuple[ctypes.CDLL, dict[str, int]]:
    """The library of ``variant`` (built if needed) and its configuration."""
    path = build(variant)
    if path not in _loaded:
        lib = ctypes.CDLL(str(path))
        _declare(lib)
        config = {name: int(lib.ups_host_config(i)) for i, name in enumerate(_CONFIG)}
        _loaded[path] = lib, config
    return _loaded[path]


def _declare(lib: ctypes.CDLL) -> None:
    p, u8, u16, u32 = ctypes.c_void_p, ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint32
    u64 = ctypes.c_uint64
    i, f = ctypes.c_int, ctypes.POINTER(_Frame)
    signatures: dict[str, tuple[Any, list[Any]]] = {
        "ups_host_node_size": (ctypes.c_size_t, []),
        "ups_host_config": (ctypes.c_long, [i]),
        "ups_init": (i, [p, u64, ctypes.c_uint]),
        "ups_start": (None, [p, u32]),
        "ups_rx": (i, [p, u32, f, ctypes.POINTER(_Event)]),
        "ups_tick": (None, [p, u32]),
        "ups_tx_peek": (f, [p]),
        "ups_tx_pop": (None, [p]),
        "ups_notes": (ctypes.c_uint, [p]),
        "ups_idle": (i, [p]),
        "ups_join_state": (i, [p]),
        "ups_txnode": (i, [p]),
        "ups_subscribe": (i, [p, u64, u32]),
        "ups_advertise": (i, [p, u64, u16, u32]),
        "ups_unsubscribe": (i, [p, i]),
        "ups_publish": (i, [p, i, ctypes.c_char_p, u16]),
        "ups_set_priority": (i, [p, i, u8]),
        "ups_channel_priority": (i, [p, i]),
        "ups_channel_state": (i, [p, i]),
        "ups_channel_etag": (u16, [p, i]),
        "ups_filters": (i, [p, ctypes.POINTER(_Filter), i]),
        "ups_declare": (i, [p, i, u8, u16, u16, u8, u32]),
        "ups_declaration_state": (i, [p, i]),
        "ups_counters": (p, [p]),
    }
    for name, (restype, argtypes) in signatures.items():
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes


def now_ms() -> int:
    """The library's clock: milliseconds, wrapping at 32 bits."""
    return int(time.monotonic() * 1000) & 0xFFFFFFFF


class CNode:
    """One C node: a ``ups_node_t`` and the calls of ``c/ups.h``."""

    def __init__(self, node_id: int, *, fd: bool = False, variant: str = "full") -> None:
        self._lib, self.config = load(variant)
        self._buf = ctypes.create_string_buffer(int(self._lib.ups_host_node_size()))
        self._node = ctypes.cast(self._buf, ctypes.c_void_p)
        self._frame = _Frame()
        self._event = _Event()
        self.node_id = node_id
        if fd and not self.config["fd"]:
            raise ConfigError("this libups was built without CAN FD (UPS_WITH_FD)")
        self._check(self._lib.ups_init(self._node, node_id, 1 if fd else 0), "init")
        counter = ctypes.c_uint16 if self.config["counter_bytes"] == 2 else ctypes.c_uint32
        self._counters_type = counter * len(COUNTERS)

    @staticmethod
    def _check(result: int, what: str) -> int:
        if result < 0:
            raise ConfigError(f"ups_{what}: {ERRORS.get(result, result)}")
        return result

    # --- the frames ------------------------------------------------------------------------

    def start(self, now: int) -> None:
        self._lib.ups_start(self._node, now)

    def rx(self, msg: can.Message, now: int) -> Event | None:
        """Feed one received frame; the event it completes, if any."""
        frame = self._frame
        data = bytes(msg.data)[:64]
        frame.id = msg.arbitration_id & 0xFFFFFFFF
        frame.flags = (
            (FRAME_EXT if msg.is_extended_id else 0)
            | (FRAME_FD if msg.is_fd else 0)
            | (FRAME_RTR if msg.is_remote_frame else 0)
            | (FRAME_ERR if msg.is_error_frame else 0)
        )
        frame.len = len(data)
        ctypes.memmove(frame.data, data, len(data))
        return self.rx_frame(frame, now)

    def rx_raw(self, can_id: int, data: bytes, flags: int, now: int) -> Event | None:
        """Feed a frame given as identifier, data and ``FRAME_...`` flags (``len`` is
        ``len(data)``, at most 64; the fuzz tests use it to feed what python-can cannot)."""
        frame = self._frame
        frame.id, frame.flags, frame.len = can_id, flags, len(data)
        ctypes.memmove(frame.data, data, len(data))
        return self.rx_frame(frame, now)

    def rx_frame(self, frame: _Frame, now: int) -> Event | None:
        if not self._lib.ups_rx(self._node, now, ctypes.byref(frame), ctypes.byref(self._event)):
            return None
        ev = self._event
        return Event(ev.channel, ctypes.string_at(ev.data, ev.size), ev.priority, ev.txnode)

    def tick(self, now: int) -> None:
        self._lib.ups_tick(self._node, now)

    def tx(self) -> Iterator[tuple[int, int, bytes]]:
        """Pop the queued frames, highest priority first, as ``(id, flags, data)``."""
        while True:
            frame = self._lib.ups_tx_peek(self._node)
            if not frame:
                return
            f = frame.contents
            item = (int(f.id), int(f.flags), bytes(f.data[: f.len]))
            self._lib.ups_tx_pop(self._node)
            yield item

    # --- state -----------------------------------------------------------------------------

    def notes(self) -> int:
        return int(self._lib.ups_notes(self._node))

    def idle(self) -> bool:
        """``ups_idle``: nothing is due, so the node may stop ticking until a frame comes or it
        calls the library again."""
        return bool(self._lib.ups_idle(self._node))

    @property
    def join_state(self) -> int:
        return int(self._lib.ups_join_state(self._node))

    @property
    def txnode(self) -> int | None:
        txnode = int(self._lib.ups_txnode(self._node))
        return None if txnode < 0 else txnode

    def counters(self) -> dict[str, int]:
        raw = self._counters_type.from_address(self._lib.ups_counters(self._node))
        return dict(zip(COUNTERS, (int(v) for v in raw), strict=True))

    def filters(self) -> list[tuple[int, int]]:
        out = (_Filter * (self.config["channels"] + 1))()
        n = int(self._lib.ups_filters(self._node, out, len(out)))
        return [(out[k].id, out[k].mask) for k in range(min(n, len(out)))]

    # --- channels --------------------------------------------------------------------------

    def subscribe(self, uid: int, now: int) -> int:
        return self._check(self._lib.ups_subscribe(self._node, uid, now), "subscribe")

    def advertise(self, uid: int, max_size: int, now: int) -> int:
        return self._check(self._lib.ups_advertise(self._node, uid, max_size, now), "advertise")

    def unsubscribe(self, channel: int) -> None:
        self._check(self._lib.ups_unsubscribe(self._node, channel), "unsubscribe")

    def publish(self, channel: int, data: bytes) -> int:
        """``ups_publish``: 0, or a negative ``UPS_ERR_...`` (see ``ERRORS``)."""
        return int(self._lib.ups_publish(self._node, channel, data, len(data)))

    def set_priority(self, channel: int, priority: int) -> None:
        self._check(self._lib.ups_set_priority(self._node, channel, priority), "set_priority")

    def channel_priority(self, channel: int) -> int:
        """``ups_channel_priority``: the priority the node's events on ``channel`` go at now
        (0x02..0xFF: the default, ``set_priority``'s, or a Grant's), or a negative
        ``UPS_ERR_...`` (no such channel)."""
        return int(self._lib.ups_channel_priority(self._node, channel))

    def channel_state(self, channel: int) -> int:
        return int(self._lib.ups_channel_state(self._node, channel))

    def channel_etag(self, channel: int) -> int:
        return int(self._lib.ups_channel_etag(self._node, channel))

    def declare(
        self, channel: int, size: int, period: int, deadline: int, jitter: int, now: int
    ) -> int:
        return int(self._lib.ups_declare(self._node, channel, size, period, deadline, jitter, now))

    def declaration_state(self, channel: int) -> int:
        return int(self._lib.ups_declaration_state(self._node, channel))


def to_message(can_id: int, flags: int, data: bytes) -> can.Message:
    return can.Message(
        arbitration_id=can_id,
        is_extended_id=bool(flags & FRAME_EXT),
        is_fd=bool(flags & FRAME_FD),
        bitrate_switch=bool(flags & FRAME_BRS),
        data=data,
    )


OnEvent = Callable[[CNode, Event, float], None]


class CNodeRunner:
    """The application loop of one or more C nodes on one python-can bus, in asyncio.

    Every millisecond it reads what the bus has, feeds each frame to every node, ticks them,
    and sends what they queued (a frame one node sends is fed to the others too: on a real
    bus they would hear it). ``on_event(node, event, timestamp)`` gets every delivered event.
    Frames the interface refuses are counted in ``tx_failed``.
    """

    def __init__(self, bus: can.BusABC, nodes: Sequence[CNode], on_event: OnEvent) -> None:
        self.bus = bus
        self.nodes = list(nodes)
        self._on_event = on_event
        self.tx_failed = 0
        self.frames_in = 0

    def start_all(self) -> None:
        now = now_ms()
        for node in self.nodes:
            node.start(now)

    def step(self) -> None:
        """One pass: receive, tick, send."""
        now = now_ms()
        for _ in range(4096):  # bounded: a flooded bus still gets ticks and sends
            msg = self.bus.recv(timeout=0)
            if msg is None:
                break
            self.frames_in += 1
            self._feed(msg, now, None)
        for node in self.nodes:
            node.tick(now)
        for _ in range(64):  # frames one node sends are heard by the others, and so on
            sent = False
            for node in self.nodes:
                for can_id, flags, data in node.tx():
                    sent = True
                    msg = to_message(can_id, flags, data)
                    try:
                        self.bus.send(msg, timeout=0.01)
                    except can.CanError:
                        self.tx_failed += 1
                    if len(self.nodes) > 1:
                        self._feed(msg, now, node)
            if not sent:
                break

    def _feed(self, msg: can.Message, now: int, sender: CNode | None) -> None:
        for node in self.nodes:
            if node is not sender:
                event = node.rx(msg, now)
                if event is not None:
                    self._on_event(node, event, msg.timestamp or time.time())

    async def run(self, until: Callable[[], bool] | None = None) -> None:
        """Run every millisecond until ``until()`` holds (or the task is cancelled)."""
        while until is None or not until():
            self.step()
            await asyncio.sleep(0.001)
