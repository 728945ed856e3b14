"""libups-ecb, the CAN-ECB in C (``c/ups_ecb.h``), compiled for this machine and called through
ctypes: the constants of its headers, ``Library`` (one compiled build), ``load`` (built on first
use with ``make -C c``, ``ups._cnode.build``) and ``HostEcb``, the backend of
``broker/c_ecb.py``'s loop that calls it (the other backend: the Cortex-M0+ image in an
emulator, ``ups/_armecb.py``).

Builds (``VARIANTS``): ``full`` (``libups-ecb.so``, the tables of a full bus with room for a
node id's whole quota of channels) or ``asan`` (``libups-ecb-asan.so``, small tables,
AddressSanitizer: load it with ``LD_PRELOAD`` of libasan).
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path
from typing import Any

from ups._cnode import build
from ups._errors import ConfigError

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
    "queries_waiting", "blob_refused", "rosters_full", "rosters", "roster_frames",
    "roster_replaced",
)  # fmt: skip
#: ups_ecb_host_config's answers, in order
CONFIG = ("nodes", "channels", "streams", "queries", "tx_depth", "held", "watched",
          "counter_bytes", "blob_max", "mtu", "rosters")  # fmt: skip


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
            "ups_ecb_channel_users": (i, [p, i, p, p]),
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


class HostEcb:
    """The backend of ``CEcb`` (``broker/c_ecb.py``'s ``Backend``) on the host build of
    ``variant``: one ``ups_ecb_t`` in this process's memory, each method one call."""

    #: a call of the host build returns (or its fault ends the process)
    errors: tuple[type[Exception], ...] = ()

    def __init__(self, variant: str = "full") -> None:
        self._lib = load(variant)
        self._c = self._lib.lib
        self.name = self._lib.path.name
        self.config = dict(self._lib.config)
        self._buf = ctypes.create_string_buffer(self._lib.size)
        self._ecb = ctypes.cast(self._buf, ctypes.c_void_p)
        self._frame = self._lib.Frame()
        self._blob = ctypes.create_string_buffer(self.config["blob_max"])
        self._word = ctypes.c_uint64()
        self._users = (ctypes.c_uint8 * 32)()  # subscribers, then publishers

    def default_config(self) -> bytes:
        cfg = Config()
        self._c.ups_ecb_default_config(ctypes.byref(cfg))
        return bytes(cfg)

    def init(self, cfg: bytes, instance: int) -> int:
        return int(self._c.ups_ecb_init(self._ecb, ctypes.byref(Config.from_buffer_copy(cfg)),
                                        instance))  # fmt: skip

    def restore(self, blob: bytes) -> int:
        return int(self._c.ups_ecb_restore(self._ecb, blob, len(blob)))

    def start(self, now: int) -> None:
        self._c.ups_ecb_start(self._ecb, now)

    def rx(self, now: int, can_id: int, flags: int, data: bytes) -> None:
        frame = self._frame
        frame.id, frame.flags, frame.len = can_id, flags, len(data)
        ctypes.memmove(frame.data, data, len(data))
        self._c.ups_ecb_rx(self._ecb, now, ctypes.byref(frame))

    def tick(self, now: int) -> None:
        self._c.ups_ecb_tick(self._ecb, now)

    def notes(self) -> int:
        return int(self._c.ups_ecb_notes(self._ecb))

    def pop_tx(self) -> tuple[int, int, bytes] | None:
        frame = self._c.ups_ecb_tx_peek(self._ecb)
        if not frame:
            return None
        f = frame.contents
        out = int(f.id), int(f.flags), bytes(f.data[: f.len])
        self._c.ups_ecb_tx_pop(self._ecb)
        return out

    def save(self) -> bytes:
        n = int(self._c.ups_ecb_save(self._ecb, self._blob, len(self._blob)))
        return self._blob.raw[:n]

    def role(self) -> int:
        return int(self._c.ups_ecb_role(self._ecb))

    def counters(self) -> tuple[int, ...]:
        raw = self._lib.Counters.from_address(self._c.ups_ecb_counters(self._ecb))
        return tuple(int(v) for v in raw)

    def node(self, i: int) -> tuple[int, int]:
        txnode = int(self._c.ups_ecb_node(self._ecb, i, ctypes.byref(self._word)))
        return txnode, self._word.value

    def channel(self, i: int) -> tuple[int, int]:
        etag = int(self._c.ups_ecb_channel(self._ecb, i, ctypes.byref(self._word)))
        return etag, self._word.value

    def channel_users(self, i: int) -> tuple[int, int, int]:
        users = self._users
        etag = int(self._c.ups_ecb_channel_users(self._ecb, i, users, ctypes.byref(users, 16)))
        raw = bytes(users)
        return etag, int.from_bytes(raw[:16], "little"), int.from_bytes(raw[16:], "little")
