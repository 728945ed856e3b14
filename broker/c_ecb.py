"""libups-ecb, the CAN-ECB in C (``c/ups_ecb.h``), from Python: its ctypes binding and the loop a
microcontroller would run it in, on any python-can bus.

``CEcb`` has the interface of the Python ``CanEcb`` that the tests and ``serve`` use (``start``,
``close``, ``instance``, ``txnodes``, ``etags``, ``stats``, ``status``, ``healthy``,
``standby``), so the conformance suite and ``ups c-ecb`` run either. It feeds every frame its
link receives to ``ups_ecb_rx`` (not its own: a controller does not hear itself), calls
``ups_ecb_tick`` every millisecond, and reads the notes after every call: on
``UPS_ECB_NOTE_STATE`` it writes the blob to ``state_path`` (a temporary file, fsync, rename)
before it sends the frames queued since, as firmware writes its flash. At start the blob is
given back with ``ups_ecb_restore``; a refused one is logged and kept aside as ``.bad``.

The library is built on first use with ``make -C c`` (``ups._cnode.build``): ``full``
(``libups-ecb.so``, the tables of a full bus with room for a node id's
whole quota of channels) or ``asan`` (``libups-ecb-asan.so``, small tables,
AddressSanitizer: load it with ``LD_PRELOAD`` of libasan).
"""

from __future__ import annotations

import asyncio
import ctypes
import fcntl
import logging
import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from ups._canlink import CanLink
from ups._cnode import build, now_ms
from ups._errors import ConfigError

from ._quota import QUOTA

log = logging.getLogger("ups.c_ecb")

RECOVERY = 2.0  #: seconds after Hello the CAN-ECB listens and adopts (CanEcb's)
LEASE = 86_400.0  #: seconds a TxNode or etag unused may be reclaimed (CanEcb's)
TICK = 0.001  #: seconds between ups_ecb_tick calls

VARIANTS = {"full": "libups-ecb.so", "asan": "libups-ecb-asan.so"}
SOURCES = ("ups.h", "ups_ecb.h", "ups_ecb_internal.h", "ups_ecb_rt.h", "ups_ecb_join.h",
           "ups_ecb_bind.h", "ups_ecb_elect.h", "ups_ecb_util.c", "ups_ecb_rt.c", "ups_ecb.c",
           "ups_ecb_join.c", "ups_ecb_bind.c", "ups_ecb_elect.c", "host/ups_ecb_host.c",
           "Makefile")  # fmt: skip

# ups.h's and ups_ecb.h's constants (tests/test_cecb_binding.py checks them against the headers)
FRAME_EXT, FRAME_FD, FRAME_BRS, FRAME_RTR, FRAME_ERR = 0x01, 0x02, 0x04, 0x08, 0x10
NOTE_STATE, NOTE_ROLE, NOTE_CHANNELS = 0x01, 0x02, 0x04
ROLES = ("stopped", "candidate", "serving", "standby")  #: UPS_ECB_STOPPED ... (CanEcb's names)
#: ups_ecb_counters_t's fields, in order
COUNTERS = (
    "joined", "bound", "requests", "malformed", "foreign", "refused", "admitted", "adopted",
    "conflicts", "foreign_ecb_frames", "unassigned", "deferred", "limited", "reclaimed",
    "offers_withdrawn", "moved", "late_claims", "quota_hit", "unanswered_takeovers",
    "census_knocks", "census_censuses", "census_stages", "census_late_stages", "census_queries",
    "census_reopened", "census_incomplete", "census_cut", "census_retries",
    "tx_dropped", "nodes_full", "channels_full", "streams_full", "held_dropped", "watched_full",
    "queries_waiting", "blob_refused", "rosters", "roster_frames", "roster_replaced",
)  # fmt: skip
#: ups_ecb_host_config's answers, in order
CONFIG = ("nodes", "channels", "streams", "queries", "tx_depth", "held", "watched",
          "counter_bytes", "blob_max", "mtu")  # fmt: skip


class Config(ctypes.Structure):
    """ups_ecb_config_t."""

    _fields_ = [("bitrate", ctypes.c_uint32), ("fd", ctypes.c_uint8),
                ("recovery_ms", ctypes.c_uint16), ("lease_s", ctypes.c_uint32),
                ("max_channels", ctypes.c_uint16), ("quota", ctypes.c_uint16 * 5)]  # fmt: skip


class Library:
    """One compiled libups-ecb: its functions, configuration and frame type."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.lib = lib = ctypes.CDLL(str(path))
        p, u32, u64, i = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint64, ctypes.c_int
        lib.ups_ecb_host_size.restype, lib.ups_ecb_host_size.argtypes = ctypes.c_size_t, []
        lib.ups_ecb_host_config.restype, lib.ups_ecb_host_config.argtypes = ctypes.c_long, [i]
        self.size = int(lib.ups_ecb_host_size())
        self.config = {n: int(lib.ups_ecb_host_config(i)) for i, n in enumerate(CONFIG)}

        class Frame(ctypes.Structure):  # ups_frame_t, of this build's UPS_MTU
            _fields_ = [("id", ctypes.c_uint32), ("flags", ctypes.c_uint8),
                        ("len", ctypes.c_uint8),
                        ("data", ctypes.c_uint8 * self.config["mtu"])]  # fmt: skip

        self.Frame = Frame
        counter = {2: ctypes.c_uint16, 4: ctypes.c_uint32, 8: ctypes.c_uint64}
        self.Counters = counter[self.config["counter_bytes"]] * len(COUNTERS)
        f, size, u64p = ctypes.POINTER(Frame), ctypes.c_size_t, ctypes.POINTER(u64)
        signatures: dict[str, tuple[Any, list[Any]]] = {
            "ups_ecb_default_config": (None, [ctypes.POINTER(Config)]),
            "ups_ecb_init": (i, [p, ctypes.POINTER(Config), u64]),
            "ups_ecb_restore": (i, [p, ctypes.c_char_p, size]),
            "ups_ecb_start": (None, [p, u32]),
            "ups_ecb_rx": (None, [p, u32, f]),
            "ups_ecb_tick": (None, [p, u32]),
            "ups_ecb_tx_peek": (f, [p]),
            "ups_ecb_tx_pop": (None, [p]),
            "ups_ecb_notes": (ctypes.c_uint, [p]),
            "ups_ecb_save": (size, [p, ctypes.c_char_p, size]),
            "ups_ecb_role": (i, [p]),
            "ups_ecb_counters": (p, [p]),
            "ups_ecb_node": (i, [p, i, u64p]),
            "ups_ecb_channel": (i, [p, i, u64p]),
            "ups_ecb_channel_use": (i, [p, i, ctypes.c_uint]),
        }
        for name, (restype, argtypes) in signatures.items():
            fn = getattr(lib, name)
            fn.restype = restype
            fn.argtypes = argtypes


_loaded: dict[Path, Library] = {}


def load(variant: str = "full") -> Library:
    """The library of ``variant`` (built if missing or older than its sources)."""
    path = build(variant, targets=VARIANTS, sources=SOURCES)
    if variant == "asan" and not _asan_loaded():  # else ASan ends the process with no error
        raise ConfigError("the asan build needs the AddressSanitizer runtime loaded first: run "
                          "with LD_PRELOAD=$(cc -print-file-name=libasan.so)")  # fmt: skip
    if path not in _loaded:
        _loaded[path] = Library(path)
    return _loaded[path]


def _asan_loaded() -> bool:
    maps = Path("/proc/self/maps")
    return "libasan" in (maps.read_text() if maps.exists() else os.environ.get("LD_PRELOAD", ""))


def default_config(variant: str = "full") -> Config:
    """ups_ecb_default_config() of ``variant``."""
    cfg = Config()
    load(variant).lib.ups_ecb_default_config(ctypes.byref(cfg))
    return cfg


def write_atomically(path: Path, data: bytes) -> None:
    """``data`` in ``path``, whole or not at all: a temporary file beside it, fsync, rename,
    fsync of the folder (so the rename is durable too)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


class CEcb:
    """libups-ecb serving the bus of ``link``, its durable state in ``state_path``.

    ``max_channels`` None: the library's default (its table's size). ``on_sent(can_id, data)``,
    when set, is called with every frame sent (after the blob was written, if it had to be).
    """

    def __init__(
        self,
        link: CanLink,
        state_path: str | Path,
        *,
        bitrate: int = 500_000,
        recovery: float = RECOVERY,
        lease: float = LEASE,
        max_channels: int | None = None,
        quota: tuple[int, int, int, int, int] = QUOTA,
        variant: str = "full",
    ) -> None:
        self.link = link
        self.state_path = Path(state_path)
        self.variant = variant
        self._lib = load(variant)
        self._c = self._lib.lib
        self.config = dict(self._lib.config)
        self._buf = ctypes.create_string_buffer(self._lib.size)
        self._ecb = ctypes.cast(self._buf, ctypes.c_void_p)
        self._frame = self._lib.Frame()
        self._blob = ctypes.create_string_buffer(self.config["blob_max"])
        self._handler = self._on_frame  # one bound method, so the link can tell it apart
        self.instance = secrets.randbits(64)
        cfg = default_config(variant)
        cfg.bitrate = bitrate
        cfg.fd = 1 if link.fd else 0
        cfg.recovery_ms = _ranged("recovery", round(recovery * 1000), 100, 10_000, "ms")
        cfg.lease_s = _ranged("lease", round(lease), 1, 0xFFFFFFFF, "s")
        if max_channels is not None:
            cfg.max_channels = _ranged("max_channels", max_channels, 1, 0xFFFF, "")
        for k, q in enumerate(quota):
            cfg.quota[k] = _ranged("quota", q, 0, 0xFFFF, "")
        if self._c.ups_ecb_init(self._ecb, ctypes.byref(cfg), self.instance) < 0:
            raise ConfigError(f"ups_ecb_init refused the configuration (recovery {recovery} s, "
                              f"bitrate {bitrate}, lease {lease} s)")  # fmt: skip
        self.bitrate = bitrate
        self.recovery = recovery
        self.storage_errors = 0
        self.storage_error: str | None = None
        self.restored = False  #: the state file's blob was taken back at start
        self.on_sent: Callable[[int, bytes], None] | None = None
        self._saved: bytes | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._started = False
        self._closed = False
        self._role = 0
        self._lock_fd = -1

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        """Take the saved blob back, then listen on the bus and say Hello (ups_ecb_start).
        ConfigError when the state file can be neither read nor written."""
        self._lock()
        self._restore()
        self._save(initial=True)  # an unwritable state file is an error now, not on a join
        self.link.add_handler(self._handler, None)
        self.link.start()
        self._started = True
        self._c.ups_ecb_start(self._ecb, now_ms())
        self._after()
        self._timer = asyncio.get_running_loop().call_later(TICK, self._tick)
        log.info(
            "CAN-ECB on %s (%s, in C): %d TxNodes, %d etags bound (%s), instance %016x",
            self.link.channel_info, self._lib.path.name, len(self.txnodes), len(self.etags),
            self.state_path, self.instance,
        )  # fmt: skip

    def close(self) -> None:
        """Stop serving the bus (the link stays open) and write the blob. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.link.remove_handler(self._handler)
        if self._started:
            self._save()
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1

    def _lock(self) -> None:
        """Hold ``STATE.lock`` (one CAN-ECB per state file), or fail naming the file."""
        path = self.state_path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(f"{path}.lock", os.O_RDONLY | os.O_CREAT, 0o644)
        except OSError as exc:
            raise ConfigError(f"cannot use the state file {path}: {exc.strerror or exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ConfigError(f"the state file {path} is in use by another CAN-ECB") from None
        self._lock_fd = fd

    def _restore(self) -> None:
        path = self.state_path
        try:
            blob = path.read_bytes()
        except FileNotFoundError:
            return
        except OSError as exc:
            raise ConfigError(f"cannot read the state file {path}: {exc.strerror}") from exc
        if self._c.ups_ecb_restore(self._ecb, blob, len(blob)) >= 0:
            self.restored = True
            self._saved = blob
            return
        bad = path.with_name(path.name + ".bad")
        try:
            os.replace(path, bad)
        except OSError as exc:
            raise ConfigError(f"cannot move the refused state file {path} aside: {exc}") from exc
        log.error("the state file %s was refused (corrupt, truncated or of other tables): kept "
                  "as %s; the CAN-ECB relearns the bus from the nodes", path, bad)  # fmt: skip

    def _save(self, *, initial: bool = False) -> bool:
        """Write the blob if it changed; False (counted, logged) when the write failed."""
        blob = self.blob()
        if not blob:
            error = f"ups_ecb_save wrote nothing (into {len(self._blob)} bytes)"
        elif blob == self._saved and not initial:
            return True
        else:
            try:
                write_atomically(self.state_path, blob)
            except OSError as exc:
                if initial:
                    raise ConfigError(
                        f"cannot write the state file {self.state_path}: {exc.strerror or exc}"
                    ) from exc
                error = f"{exc.strerror or exc}"
            else:
                self._saved = blob
                self.storage_error = None
                return True
        self.storage_errors += 1
        self.storage_error = error
        log.error("C CAN-ECB could not write its state to %s: %s", self.state_path, error)
        return False

    # --- the loop --------------------------------------------------------------------------

    def _tick(self) -> None:
        self._timer = asyncio.get_running_loop().call_later(TICK, self._tick)
        self._c.ups_ecb_tick(self._ecb, now_ms())
        self._after()

    def _on_frame(self, msg: can.Message) -> None:
        frame = self._frame
        mtu = self.config["mtu"]
        data = bytes(msg.data)[:mtu]  # a controller of this MTU keeps no more of a frame
        frame.id = msg.arbitration_id & 0x1FFFFFFF
        frame.flags = (
            (FRAME_EXT if msg.is_extended_id else 0)
            | (FRAME_FD if msg.is_fd else 0)
            | (FRAME_BRS if msg.bitrate_switch else 0)
            | (FRAME_RTR if msg.is_remote_frame else 0)
            | (FRAME_ERR if msg.is_error_frame else 0)
        )
        frame.len = len(data)
        ctypes.memmove(frame.data, data, len(data))
        self._c.ups_ecb_rx(self._ecb, now_ms(), ctypes.byref(frame))
        self._after()

    def _after(self) -> None:
        """What a call left to do: the blob first (on NOTE_STATE), then the frames."""
        notes = int(self._c.ups_ecb_notes(self._ecb))
        if notes & NOTE_ROLE:
            self._role_changed()
        durable = not notes & NOTE_STATE or self._save()
        c = self._c
        while frame := c.ups_ecb_tx_peek(self._ecb):
            f = frame.contents
            can_id, flags, data = int(f.id), int(f.flags), bytes(f.data[: f.len])
            c.ups_ecb_tx_pop(self._ecb)
            if not durable:  # what a reset would forget is not announced: the asker retries
                continue
            self.link.send(can_id, data, self._handler, fd=bool(flags & FRAME_FD))
            if self.on_sent is not None:
                self.on_sent(can_id, data)

    def _role_changed(self) -> None:
        role = int(self._c.ups_ecb_role(self._ecb))
        before, self._role = self._role, role
        if ROLES[role] == "standby":
            log.error("another CAN-ECB already serves this bus: this CAN-ECB stands by and "
                      "answers nothing")  # fmt: skip
        elif ROLES[before] == "standby":
            log.warning("the CAN-ECB that served went silent or left a request unanswered: "
                        "this one serves the bus again")  # fmt: skip

    # --- tables and statistics -------------------------------------------------------------

    @property
    def role(self) -> str:
        return ROLES[int(self._c.ups_ecb_role(self._ecb))]

    @property
    def standby(self) -> bool:
        """Another CAN-ECB serves the bus."""
        return self.role == "standby"

    @property
    def healthy(self) -> bool:
        """False while writing the state fails or another CAN-ECB serves the bus."""
        return self.storage_error is None and not self.standby

    @property
    def txnodes(self) -> dict[int, int]:
        """node id -> TxNode, every assignment of the tables."""
        out: dict[int, int] = {}
        node_id = ctypes.c_uint64()
        for i in range(self.config["nodes"]):
            txnode = int(self._c.ups_ecb_node(self._ecb, i, ctypes.byref(node_id)))
            if txnode >= 0:
                out[node_id.value] = txnode
        return out

    @property
    def etags(self) -> dict[int, int]:
        """channel UID -> etag, every binding of the tables."""
        return {uid: etag for _, uid, etag in self._channels()}

    def _channels(self) -> list[tuple[int, int, int]]:
        out = []
        uid = ctypes.c_uint64()
        for i in range(self.config["channels"]):
            etag = int(self._c.ups_ecb_channel(self._ecb, i, ctypes.byref(uid)))
            if etag >= 0:
                out.append((i, uid.value, etag))
        return out

    def blob(self) -> bytes:
        """What ups_ecb_save() writes now (empty: it wrote nothing)."""
        n = int(self._c.ups_ecb_save(self._ecb, self._blob, len(self._blob)))
        return self._blob.raw[:n]

    def counters(self) -> dict[str, int]:
        """ups_ecb_counters(), by name."""
        raw = self._lib.Counters.from_address(self._c.ups_ecb_counters(self._ecb))
        return dict(zip(COUNTERS, (int(v) for v in raw), strict=True))

    def stats(self) -> dict[str, object]:
        return {
            **self.counters(),
            "storage_errors": self.storage_errors,
            "txnodes": len(self.txnodes),
            "etags": len(self.etags),
            "storage_error": self.storage_error,
            "state": str(self.state_path),
            "healthy": self.healthy,
            "standby": self.standby,
            "role": self.role,
            "instance": f"{self.instance:016x}",
        }

    def status(self) -> dict[str, Any]:
        """The tables as ``ups status`` and ``ups ls`` show them (CanEcb.status()'s shape)."""
        txnodes = self.txnodes
        held = sorted(set(txnodes.values()))
        use = self._c.ups_ecb_channel_use
        channels = []
        for i, uid, etag in sorted(self._channels(), key=lambda c: c[2]):
            uses = {t: int(use(self._ecb, i, t)) for t in held}
            channels.append({
                "uid": f"0x{uid:016x}", "etag": f"0x{etag:04x}",
                "publishers": [f"0x{t:02x}" for t in held if uses[t] & 2],
                "subscribers": [f"0x{t:02x}" for t in held if uses[t] & 1],
            })  # fmt: skip
        return {
            "nodes": [{"node_id": f"0x{n:016x}", "txnode": f"0x{t:02x}"}
                      for n, t in sorted(txnodes.items(), key=lambda i: i[1])],
            "channels": channels,
            "stats": self.stats(),
        }  # fmt: skip


def _ranged(name: str, value: int, low: int, high: int, unit: str) -> int:
    if not low <= value <= high:
        raise ConfigError(f"{name} must be {low}..{high}{' ' + unit if unit else ''}: {value}")
    return value


async def serve(
    bus: str, state_path: str | Path, bitrate: int = 500_000, status: str | None = None,
    metrics: str | None = None, **options: Any,
) -> int:  # fmt: skip
    """Run libups-ecb as the CAN-ECB of ``bus`` until cancelled (``CanEcb``'s ``serve``: with
    ``status`` (HOST:PORT) its tables served to ``ups status`` and ``ups ls``, with ``metrics``
    its counters to Prometheus). The blob is written when the run ends. Returns 1 if writing
    the state file failed during the run, else 0."""
    from ._serving import run

    def make(link: CanLink) -> CEcb:
        return CEcb(link, state_path, bitrate=bitrate, **options)

    ecb = await run(bus, make, "c-ecb", status, metrics)
    if ecb.storage_errors:
        log.error("the state file %s could not be written %d times", state_path,
                  ecb.storage_errors)  # fmt: skip
    return 1 if ecb.storage_errors else 0
