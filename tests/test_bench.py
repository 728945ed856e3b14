"""``ups bench``: its command line, and its report built from small real measurements (the
whole run is a benchmark, not a test: timings are never asserted here)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from ups.benchmarks import _compiled, _report, bench, fanout, tcp_payload

from .procs import ROOT

REQUIRED = ("local_notify_us", "publish_latency_us", "rtt_us", "throughput_msgs_per_s", "peers")


def test_ups_bench_has_its_command_line() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "upscli", "bench", "--help"], cwd=ROOT, capture_output=True,
        text=True, timeout=60, check=True,
    )  # fmt: skip
    for option in ("--quick", "--json", "--report"):
        assert option in done.stdout


def test_a_report_from_real_parts_says_what_it_measured_and_what_it_did_not(
    tmp_path: Path,
) -> None:
    results = {
        "machine": bench.machine(quick=True),
        "skipped": {"table5": "needs root (in this test: not run)"},
        "failed": {},
        "startup_s": bench.startup(quick=True),
        "code_size": bench.code_size(),
        "payload": tcp_payload.run((8, 1024), mib=0.25),
        "fanout": fanout.run((1, 2), 2000),
    }
    results.update(bench.summary(results))
    assert set(REQUIRED) <= set(results)
    assert results["local_notify_us"] is None and results["rtt_us"] == {}  # not run: not made up
    assert all(row["ups"]["received"] == row["count"] for row in results["payload"])
    assert all(row["ups"]["lost"] == 0 for row in results["fanout"])
    if _compiled.unavailable() is None:  # the compiled build runs beside, as lossless
        assert all(row["ups_compiled"]["received"] == row["subscribers"] * 2000
                   for row in results["fanout"])  # fmt: skip
    targets = {t["target"]: t for t in results["targets"]}
    assert targets["round trip p50 <= 2x raw TCP"]["met"] is None  # tcp_compare did not run
    assert targets["ups --help <= 3x python -c pass"]["met"] == (results["startup_s"]["ratio"] <= 3)
    _report.write(results, tmp_path / "report")
    text = (tmp_path / "report" / "report.md").read_text()
    met = "met" if results["startup_s"]["ratio"] <= 3 else "MISSED"
    assert "ups --help <= 3x python -c pass" in text and f"| {met} |" in text
    assert "round trip p50 <= 2x raw TCP" in text and "not measured" in text
    assert "skipped table5: needs root" in text
    assert results["machine"]["python"] in text and "## Machine" in text
    doc = json.loads((tmp_path / "report" / "results.json").read_text())
    assert doc["payload"] and doc["targets"] and set(REQUIRED) <= set(doc)
    if importlib.util.find_spec("matplotlib") is None:
        pytest.skip("matplotlib is not installed: the report has no plots (ups-pubsub[bench])")
    for name in ("payload.png", "fanout.png"):
        png = (tmp_path / "report" / name).read_bytes()
        assert png.startswith(b"\x89PNG") and f"]({name})" in text


def test_the_text_table_shows_a_peer_that_could_not_run_as_skipped() -> None:
    rows = {
        "raw TCP": {"rtt_p50_us": 15.0, "rtt_p99_us": 40.0, "rate_msg_s": 2e5, "lost": 0,
                    "error": ""},
        "zenoh peer-to-peer": {"error": "skipped: eclipse-zenoh is not installed"},
        "UPS TCP, uvloop": {"rtt_p50_us": 30.0, "rtt_p99_us": 80.0, "rate_msg_s": 3e5,
                            "lost": 0, "error": ""},
    }  # fmt: skip
    results = {"machine": bench.machine(quick=True), "skipped": {}, "failed": {},
               "tcp_compare": {"rows": rows, "environment": {}}}  # fmt: skip
    results.update(bench.summary(results))
    out = _report.text(results)
    assert "skipped: eclipse-zenoh is not installed" in out
    assert results["peers"]["zenoh"]["rtt_p50_us"] is None
    assert results["peers"]["raw_tcp"]["rtt_p50_us"] == 15.0
    targets = {t["target"]: t for t in results["targets"]}
    assert targets["round trip p50 <= 2x raw TCP"]["measured"] == 2.0
    assert targets["round trip p50 <= 2x raw TCP"]["met"] is True
    assert targets["throughput above zenoh, zero loss"]["met"] is None


def test_the_compiled_build_is_judged_on_its_own_beside_the_pure_one() -> None:
    row = {"rtt_p99_us": 80.0, "lost": 0, "error": ""}
    rows = {
        "raw TCP": {**row, "rtt_p50_us": 10.0, "rate_msg_s": 2e5},
        "pyzmq PUB/SUB, HWM=0": {**row, "rtt_p50_us": 30.0, "rate_msg_s": 1e6},
        "UPS TCP, uvloop": {**row, "rtt_p50_us": 35.0, "rate_msg_s": 5e5},
        "UPS TCP, uvloop, compiled": {**row, "rtt_p50_us": 25.0, "rate_msg_s": 7e5},
    }
    fan = {"subscribers": 16, "ratio": 0.3, "ratio_compiled": 0.55,
           "ups": {"lost": 0}, "ups_compiled": {"lost": 3}}  # fmt: skip
    results = {"tcp_compare": {"rows": rows}, "fanout": [fan]}
    targets = {name: (value, met) for name, value, _, met in _report.targets(results)}
    assert targets["round trip p50 below every peer"] == (35.0 / 30.0, False)
    assert targets["round trip p50 below every peer, compiled"] == (25.0 / 30.0, True)
    assert targets["throughput >= 0.6x pyzmq, zero loss, compiled"] == (0.7, True)
    assert targets["lossless fan-out >= 0.5x pyzmq at 16"] == (0.3, False)
    assert targets["lossless fan-out >= 0.5x pyzmq at 16, compiled"] == (0.55, False)  # lost 3


def test_round_trips_are_shared_among_process_pairs(tmp_path: Path) -> None:
    """tcp_compare's round trip: each pair of processes its own address layout, the figure over
    all of them; each pair's p50 is kept, and the report shows their span."""
    out = tmp_path / "rtt.json"
    subprocess.run(
        [sys.executable, "-m", "ups.benchmarks.tcp_compare", "--peers", "raw,ups", "--pairs", "3",
         "--roundtrips", "61", "--warmup", "5", "--messages", "2000", "--json", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    rows = {row["peer"]: row for row in json.loads(out.read_text())["rows"]}
    for label in ("raw TCP", "UPS TCP, uvloop"):
        row = rows[label]
        assert not row["error"], row["error"]
        assert row["roundtrips"] == 61  # 21 + 20 + 20, every one counted once
        assert len(row["rtt_p50_pairs_us"]) == 3
        low, high = min(row["rtt_p50_pairs_us"]), max(row["rtt_p50_pairs_us"])
        assert low - 1e-9 <= row["rtt_p50_us"] <= high + 1e-9  # the pooled median lies between
    table = _report.tables({"tcp_compare": {"rows": rows}})
    (peers,) = [t for t in table if t[0].startswith("Round trip")]
    assert "p50 of each pair" in peers[1]
