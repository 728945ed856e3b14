"""libups-ecb call by call, for the tests of its parts (tests/test_cecb_join.py,
tests/test_cecb_bind.py): one ``ups_ecb_t`` whose time the test gives, fed frames built from
the document (tests/conformance/_frames.py), and what it sends decoded the same way."""

from __future__ import annotations

import ctypes
from typing import Any

from tests.cecb_driver import config
from tests.conformance._frames import decode_id, encode
from ups.broker._cecb_lib import COUNTERS, load


class Driver:
    """One ups_ecb_t of ``variant`` (``cfg``: ups_ecb_config_t's fields, ``quota`` a tuple),
    ticked every ``step`` ms by :meth:`tick`."""

    def __init__(self, variant: str, step: int = 5, **cfg: Any) -> None:
        self.lib = load(variant)
        self.c = self.lib.lib
        self.config = self.lib.config
        self.state = ctypes.create_string_buffer(self.lib.size)
        self.frame = self.lib.Frame()
        self.step = step
        conf = config(variant, **cfg)
        assert self.c.ups_ecb_init(self.state, ctypes.byref(conf), 0x1D) == 0
        self.now = 0

    def start(self, now: int) -> list[Any]:
        self.now = now
        self.c.ups_ecb_start(self.state, now)
        return self.take()

    def rx(self, *frames: Any) -> list[Any]:
        """Feed ``frames`` one by one; what it sent after each."""
        out = []
        for frame in frames:
            can_id, data = encode(frame)
            self.frame.id, self.frame.flags, self.frame.len = can_id, 0x01, len(data)
            ctypes.memmove(self.frame.data, data, len(data))
            self.c.ups_ecb_rx(self.state, self.now, ctypes.byref(self.frame))
            out += self.take()
        return out

    def tick(self, ms: int) -> list[Any]:
        """Pass ``ms`` milliseconds, ticking every ``step``."""
        out = []
        for _ in range(0, ms, self.step):
            self.now = (self.now + self.step) & 0xFFFFFFFF
            self.c.ups_ecb_tick(self.state, self.now)
            out += self.take()
        return out

    def take(self) -> list[Any]:
        out = []
        while frame := self.c.ups_ecb_tx_peek(self.state):
            f = frame.contents
            out.append(decode_id(int(f.id), bytes(f.data[: f.len])))
            self.c.ups_ecb_tx_pop(self.state)
        return out

    def counters(self) -> dict[str, int]:
        raw = self.lib.Counters.from_address(self.c.ups_ecb_counters(self.state))
        return dict(zip(COUNTERS, (int(v) for v in raw), strict=True))

    def nodes(self) -> dict[int, int]:
        node_id = ctypes.c_uint64()
        out = {}
        for i in range(self.config["nodes"]):
            t = self.c.ups_ecb_node(self.state, i, ctypes.byref(node_id))
            if t >= 0:
                out[node_id.value] = t
        return out

    def save(self) -> bytes:
        blob = ctypes.create_string_buffer(self.config["blob_max"])
        n = self.c.ups_ecb_save(self.state, blob, len(blob))
        return blob.raw[:n]
