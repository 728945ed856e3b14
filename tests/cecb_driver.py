"""libups-ecb driven call by call for tests/test_cecb_fuzz.py: its state, frames and blobs in
memory of the C allocator (under ASan, with red zones around them, so that a read or a write
past the end of the state, a frame or a blob aborts the process), and its tables and counters
read back through its API.

The library is ``ups.broker.c_ecb``'s (``load``: its ctypes signatures and configuration), or
the one at ``$UPS_CECB_FUZZ_LIB`` (a copy built elsewhere); nothing of the CAN-ECB is mocked.
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path
from typing import Any

from ups.broker._cecb_lib import COUNTERS, Config, Library, load

STOPPED, CANDIDATE, SERVING, STANDBY = range(4)
NOTE_STATE = 0x01
FRAME_EXT, FRAME_FD, FRAME_BRS, FRAME_RTR, FRAME_ERR = 0x01, 0x02, 0x04, 0x08, 0x10

_libc = ctypes.CDLL(None)
_libc.malloc.restype = ctypes.c_void_p
_libc.malloc.argtypes = [ctypes.c_size_t]
_libc.free.restype = None
_libc.free.argtypes = [ctypes.c_void_p]


class _Block:
    """``size`` bytes from malloc (ASan's, when it is preloaded), exactly: no slack after them."""

    def __init__(self, size: int, data: bytes = b"") -> None:
        self.size = size
        self.addr = int(_libc.malloc(max(size, 1)))
        assert self.addr, "malloc failed"
        ctypes.memset(self.addr, 0xA5, max(size, 1))
        ctypes.memmove(self.addr, data, len(data))

    def read(self, n: int) -> bytes:
        return ctypes.string_at(self.addr, n)

    def free(self) -> None:
        if self.addr:
            _libc.free(self.addr)
            self.addr = 0


_libs: dict[str, Library] = {}


def library(variant: str) -> Library:
    """libups-ecb of ``variant``; for ``asan``, the one at ``$UPS_CECB_FUZZ_LIB`` if set."""
    path = os.environ.get("UPS_CECB_FUZZ_LIB")
    if path is None or variant != "asan":
        return load(variant)
    if path not in _libs:
        _libs[path] = Library(Path(path))
    return _libs[path]


def config(variant: str, **fields: Any) -> Config:
    """ups_ecb_default_config() of ``variant`` with ``fields`` changed (quota: a tuple)."""
    cfg = Config()
    library(variant).lib.ups_ecb_default_config(ctypes.byref(cfg))
    for name, value in fields.items():
        if name == "quota":
            for k, q in enumerate(value):
                cfg.quota[k] = q
        else:
            setattr(cfg, name, value)
    return cfg


class Ecb:
    """One ups_ecb_t: init (``cfg``, ``instance``), then the API's calls."""

    def __init__(self, variant: str, cfg: Config, instance: int) -> None:
        self.lib = library(variant)
        self.c = self.lib.lib
        self.config = self.lib.config
        rosters = self.c.ups_ecb_host_rosters  # c/host/ups_ecb_host.c's, for the tests
        rosters.restype, rosters.argtypes = ctypes.c_uint, [ctypes.c_void_p, ctypes.c_char_p]
        self.state = _Block(self.lib.size)
        self.frame = _Block(ctypes.sizeof(self.lib.Frame))
        self._frame = ctypes.cast(self.frame.addr, ctypes.POINTER(self.lib.Frame))
        self.instance = instance
        self._counters: Any = None
        rc = self.c.ups_ecb_init(self.state.addr, ctypes.byref(cfg), instance)
        assert rc == 0, f"ups_ecb_init: {rc}"

    def close(self) -> None:
        self.state.free()
        self.frame.free()

    # --- the calls -------------------------------------------------------------------------

    def restore(self, blob: bytes) -> int:
        block = _Block(len(blob), blob)
        try:
            ptr = ctypes.cast(block.addr, ctypes.c_char_p)
            return int(self.c.ups_ecb_restore(self.state.addr, ptr, len(blob)))
        finally:
            block.free()

    def start(self, now: int) -> None:
        self.c.ups_ecb_start(self.state.addr, now)

    def rx(self, now: int, can_id: int, flags: int, data: bytes) -> None:
        assert len(data) <= self.config["mtu"], "a frame larger than ups_frame_t"
        f = self._frame.contents
        f.id, f.flags, f.len = can_id, flags, len(data)
        ctypes.memmove(f.data, data, len(data))
        self.c.ups_ecb_rx(self.state.addr, now, self._frame)

    def tick(self, now: int) -> None:
        self.c.ups_ecb_tick(self.state.addr, now)

    def take(self) -> list[tuple[int, int, bytes]]:
        """Every frame queued, in the order ups_ecb_tx_peek gives them."""
        out = []
        while frame := self.c.ups_ecb_tx_peek(self.state.addr):
            f = frame.contents
            assert f.len <= self.config["mtu"], f"a frame of {f.len} bytes queued"
            out.append((int(f.id), int(f.flags), bytes(f.data[: f.len])))
            self.c.ups_ecb_tx_pop(self.state.addr)
            assert len(out) <= self.config["tx_depth"], "more frames than the TX queue holds"
        return out

    def notes(self) -> int:
        return int(self.c.ups_ecb_notes(self.state.addr))

    def save(self, cap: int | None = None) -> bytes:
        """ups_ecb_save into exactly ``cap`` bytes (UPS_ECB_BLOB_MAX by default)."""
        cap = self.config["blob_max"] if cap is None else cap
        block = _Block(cap)
        try:
            n = int(self.c.ups_ecb_save(self.state.addr, ctypes.cast(block.addr, ctypes.c_char_p),
                                        cap))  # fmt: skip
            assert n <= cap, f"ups_ecb_save says {n} bytes into {cap}"
            return block.read(n)
        finally:
            block.free()

    # --- what it tells -----------------------------------------------------------------------

    def role(self) -> int:
        return int(self.c.ups_ecb_role(self.state.addr))

    def counters(self) -> dict[str, int]:
        if self._counters is None:
            address = self.c.ups_ecb_counters(self.state.addr)
            self._counters = self.lib.Counters.from_address(address)
        return dict(zip(COUNTERS, self._counters[:], strict=True))

    def nodes(self) -> dict[int, int]:
        """TxNode -> node id; asserts that no TxNode and no node id is in two entries."""
        out: dict[int, int] = {}
        value = ctypes.c_uint64()
        n = self.config["nodes"]
        for i in (-1, n, n + 1):
            assert self.c.ups_ecb_node(self.state.addr, i, ctypes.byref(value)) == -1
        for i in range(n):
            txnode = int(self.c.ups_ecb_node(self.state.addr, i, ctypes.byref(value)))
            if txnode < 0:
                assert txnode == -1, f"ups_ecb_node({i}) = {txnode}"
                continue
            assert txnode < 0x7F, f"entry {i}: TxNode {txnode:#x}"
            assert txnode not in out, (
                f"TxNode {txnode:#x} held by {out.get(txnode, 0):#x} and {value.value:#x}"
            )
            assert value.value not in out.values(), f"node id {value.value:#x} holds two TxNodes"
            out[txnode] = value.value
        return out

    def channels(self) -> dict[int, tuple[int, int]]:
        """etag -> (uid, entry index); asserts that no etag and no UID is in two entries, and
        that ups_ecb_channel_users agrees (the etag, users only of TxNodes held)."""
        out: dict[int, tuple[int, int]] = {}
        value = ctypes.c_uint64()
        n = self.config["channels"]
        for i in (-1, n, n + 1):
            assert self.c.ups_ecb_channel(self.state.addr, i, ctypes.byref(value)) == -1
            assert self.users(i) == (-1, 0, 0), f"ups_ecb_channel_users({i})"
        held = sum(1 << t for t in self.nodes())  # users are TxNodes held, of this etag
        uids = set()
        for i in range(n):
            etag = int(self.c.ups_ecb_channel(self.state.addr, i, ctypes.byref(value)))
            users = self.users(i)
            assert users[0] == etag and (users[1] | users[2]) & ~held == 0, f"entry {i}: {users}"
            if etag < 0:
                assert etag == -1, f"ups_ecb_channel({i}) = {etag}"
                continue
            assert 0x10 <= etag <= 0x3FFF, f"entry {i}: etag {etag:#x}"
            assert etag not in out, (
                f"etag {etag:#x} bound to {out[etag][0]:#x} and {value.value:#x}"
            )
            assert value.value not in uids, f"UID {value.value:#x} bound to two etags"
            uids.add(value.value)
            out[etag] = (value.value, i)
        return out

    def users(self, index: int) -> tuple[int, int, int]:
        """ups_ecb_channel_users: the etag (-1: an unused entry), then the TxNodes that
        subscribe and those that publish (bit t: TxNode t); each map its own 16 bytes (red
        zones around them), zero for an unused entry."""
        maps = _Block(16), _Block(16)
        try:
            etag = int(self.c.ups_ecb_channel_users(self.state.addr, index, maps[0].addr,
                                                    maps[1].addr))  # fmt: skip
            subs, pubs = (int.from_bytes(m.read(16), "little") for m in maps)
        finally:
            for m in maps:
                m.free()
        assert etag >= 0 or subs == pubs == 0, f"ups_ecb_channel_users({index}) = {etag}: users"
        return etag, subs, pubs

    def rosters(self) -> list[int]:
        """The node entries whose Rosters wait, oldest first (ups_ecb_host_rosters)."""
        slots = ctypes.create_string_buffer(128)
        n = int(self.c.ups_ecb_host_rosters(self.state.addr, slots))
        return list(slots.raw[:n])


def tables_of(variant: str, cfg: Config, blob: bytes) -> tuple[dict[int, int], dict[int, int]]:
    """The tables (TxNode -> node id, etag -> uid) a fresh CAN-ECB takes back from ``blob``."""
    ecb = Ecb(variant, cfg, 1)
    try:
        rc = ecb.restore(blob)
        assert rc == 0, f"ups_ecb_restore refused the blob ups_ecb_save wrote ({rc}): {blob.hex()}"
        return ecb.nodes(), {e: u for e, (u, _) in ecb.channels().items()}
    finally:
        ecb.close()
