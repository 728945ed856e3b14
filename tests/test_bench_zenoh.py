"""``benchmarks/zenoh_face``: a tiny real run gives every figure and its ratios, and ``ups bench``
reports them; a run out of time says so and leaves no process behind. Timings are never
asserted here (a benchmark, not a test)."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ups.benchmarks import _report, bench, zenoh_face

from .procs import ROOT

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("zenoh") is None, reason="eclipse-zenoh is not installed"
)
TINY = ["--roundtrips", "50", "--warmup", "10", "--messages", "3000", "--gateway-events", "500",
        "--gateway-runs", "1", "--refine", "0"]  # fmt: skip


def run(tmp_path: Path, *args: str, timeout: float = 180) -> tuple[int, dict[str, object], str]:
    """``python -m ups.benchmarks.zenoh_face ARGS`` in a session of its own; after it exits, no
    process of that session may be left."""
    out = tmp_path / "zenoh.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "ups.benchmarks.zenoh_face", *args, "--json", str(out)], cwd=ROOT,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        output, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, 9)
            proc.wait(10)
    deadline = time.monotonic() + 10  # children killed on the way out: give them a moment
    while (left := session_members(proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not left, f"left running: {left}"
    return proc.returncode, json.loads(out.read_text()), output


def session_members(sid: int) -> list[str]:
    members = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[3]) == sid and fields[0] != "Z":  # fields[3]: the session id
            members.append(cmdline.decode(errors="replace")[:120])
    return members


def test_a_tiny_run_measures_every_figure_and_its_ratios(tmp_path: Path) -> None:
    code, doc, output = run(tmp_path, *TINY)
    assert code == 0, output
    assert doc["errors"] == {}
    for table, labels in (
        ("rtt", (zenoh_face.UPS_ZENOH, zenoh_face.RAW, zenoh_face.UPS_TCP)),
        ("one_way", (zenoh_face.UPS_ZENOH, zenoh_face.RAW, zenoh_face.RAW_BLOCK,
                     zenoh_face.UPS_TCP)),
        ("gateway", (zenoh_face.GW_ZENOH, zenoh_face.GW_TCP, zenoh_face.GW_FLOOR)),
    ):  # fmt: skip
        assert set(labels) <= set(doc[table]), table  # type: ignore[call-overload]
    gateway = doc["gateway"][zenoh_face.GW_ZENOH]  # type: ignore[index]
    assert gateway["runs"][0]["forwarded"] == 500  # every frame went out to Zenoh
    flat_out = doc["one_way"][zenoh_face.UPS_ZENOH]  # type: ignore[index]
    assert flat_out["counted_lost"] == flat_out["lost"], flat_out  # every loss counted, in its step
    ratios = doc["ratios"]
    for figure in ("rtt_p50_us", "rtt_p99_us", "one_way_rate", "gateway_rate"):
        assert set(ratios[figure]) == {"vs_raw_zenoh", "vs_ups_tcp"}  # type: ignore[index]
    assert ratios["rtt_p50_us"]["vs_raw_zenoh"] > 0  # type: ignore[index]
    assert "UPS Zenoh / raw zenoh" in output and "UPS Zenoh / UPS TCP" in output

    results = {"machine": bench.machine(quick=True), "skipped": {}, "failed": {},
               "zenoh_face": doc}  # fmt: skip
    results.update(bench.summary(results))
    assert results["zenoh"]["rtt_us"]["p50"] == doc["rtt"][zenoh_face.UPS_ZENOH]["p50_us"]  # type: ignore[index]
    text = _report.markdown(results, [])
    assert "## UPS Zenoh face against raw zenoh and UPS TCP" in text
    assert "Zenoh face, gateway CAN -> IP" in text and "benchmarks/zenoh_face.py" in text


def test_a_run_out_of_time_says_so_and_stops_what_it_started(tmp_path: Path) -> None:
    started = time.monotonic()
    code, doc, output = run(tmp_path, *TINY, "--time-limit", "4")
    assert code == 1, output
    assert "time limit" in doc["errors"]  # type: ignore[operator]
    assert time.monotonic() - started < 60
