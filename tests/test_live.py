"""The live model behind ``ups monitor`` and ``ups console``: its bounds hold and are counted,
rates are events per second, a silent CAN node is shown as such."""

from __future__ import annotations

from ups._catalog import Catalog
from ups.tools import _live
from ups.tools._live import Live

CATALOG = Catalog.from_text('[channel."speed"]\nfields = [{ name = "v", type = "u8" }]\n')


def test_every_bound_holds_and_is_counted() -> None:
    live = Live(CATALOG, "can", "virtual:x")
    for uid in range(_live.MAX_CHANNELS + 5):
        live.event(1000.0, uid, 0x10, "0x01", 0x80, b"")
    for n in range(_live.MAX_NODES + 3):
        live.node(1000.0, f"0x{n:016x}", txnode=n % 127)
    snap = live.snapshot(1000.5)
    assert len(snap["channels"]) == _live.MAX_CHANNELS
    assert len(snap["nodes"]) == _live.MAX_NODES
    assert snap["counters"]["untracked"] == 5 + 3
    assert len(snap["recent"]) == _live.RECENT


def test_rates_values_history_and_silence() -> None:
    live = Live(CATALOG, "can", "virtual:x", bitrate=500_000)
    (spec,) = CATALOG
    t = 1000.0
    for i in range(_live.HISTORY + 100):  # 100 events a second for 7 s
        t = 1000.0 + i / 100
        live.event(t, spec.uid, 0x10, "0x01", 0x80, bytes([i % 256]))
        live.frame_bits(t, 100)
    live.node(t, "0x00000000000000a1", txnode=1)
    snap = live.snapshot(t)
    (chan,) = snap["channels"]
    assert chan["name"] == "speed" and chan["etag"] == "0x0010"
    assert 90 <= chan["rate"] <= 110  # events per second over the window
    assert (
        chan["last"] == f"v={(_live.HISTORY + 99) % 256}" and chan["count"] == _live.HISTORY + 100
    )
    assert len(live.history(chan["key"])) == _live.HISTORY  # the plot's points are bounded
    assert 0.015 <= snap["bus_load"] <= 0.025  # 100 frames of 100 bits a second at 500 kbit/s
    later = live.snapshot(t + _live.SILENT + 1)
    assert later["nodes"][0]["alive"] is False and "silent" in later["recent"][-1]
    live.node(t + 10, "0x00000000000000a1", txnode=1)
    assert "back" in live.snapshot(t + 10)["recent"][-1]
