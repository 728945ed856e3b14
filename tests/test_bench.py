"""``ups bench``: its command line, and its report built from small real measurements (the
whole run is a benchmark, not a test: timings are never asserted here)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import _report, bench, tcp_payload

from .procs import ROOT

REQUIRED = ("local_notify_us", "publish_latency_us", "rtt_us", "throughput_msgs_per_s", "peers")


def test_ups_bench_has_its_command_line() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "ups.cli", "bench", "--help"], cwd=ROOT, capture_output=True,
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
        "startup": bench.startup(quick=True),
        "code_size": bench.code_size(),
        "payload": tcp_payload.run((8, 1024), mib=0.25),
    }
    results.update(bench.summary(results))
    assert set(REQUIRED) <= set(results)
    assert results["local_notify_us"] is None and results["rtt_us"] == {}  # not run: not made up
    assert all(row["ups"]["received"] == row["count"] for row in results["payload"])
    _report.write(results, tmp_path / "report")
    text = (tmp_path / "report" / "report.md").read_text()
    met = "met" if results["startup"]["ratio"] <= 3 else "MISSED"
    assert "ups --help <= 3x python -c pass" in text and met in text
    assert "round trip p50 <= 2x raw TCP" in text and "not measured" in text
    assert "table5: needs root" in text
    assert json.loads((tmp_path / "report" / "results.json").read_text())["payload"]
    if importlib.util.find_spec("matplotlib") is None:
        pytest.skip("matplotlib is not installed: the report has no plots (ups-pubsub[bench])")
    png = (tmp_path / "report" / "payload.png").read_bytes()
    assert png.startswith(b"\x89PNG") and "payload.png" in text
