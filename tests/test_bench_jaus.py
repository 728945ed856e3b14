"""``benchmarks/jaus_paper000``: a tiny real run (CAN-ECB, CAN echo, two ``ups jaus``
processes) gives every path of paper 000's Table 2 beside the UPS CAN path, with nothing lost,
and the reports per second; ``ups bench`` reports them beside the paper. Timings are never
asserted here (a benchmark, not a test)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ups.benchmarks import _report, bench, jaus_paper000

from .procs import ROOT, private_multicast_bus

TINY = ["--messages", "20", "--warmup", "2", "--gap", "2", "--report-seconds", "0.5"]


def test_a_tiny_run_measures_every_path_beside_table_2(tmp_path: Path) -> None:
    private_multicast_bus()  # udp_multicast: only inside a private namespace
    out = tmp_path / "jaus.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "ups.benchmarks.jaus_paper000", *TINY, "--json", str(out)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        stdin=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        stdout, stderr = proc.communicate(timeout=50)
    finally:  # its daemons too, whatever happened: the session is theirs alone
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    assert proc.returncode == 0, stderr[-3000:]
    doc = json.loads(out.read_text())
    assert set(doc["paths"]) == set(jaus_paper000.PATHS)
    for key, row in doc["paths"].items():
        assert (row["n"], row["lost"]) == (20, 0), key  # every message answered
        figures = row["one_way_ms"]
        assert figures["min"] <= figures["mean"] <= figures["max"], key
    assert doc["paths"]["ra33_direct"]["message_bytes"] == 17  # the paper's minimal message
    assert doc["echo"]["dropped"] == 0
    periodic = doc["reports"]["periodic"]
    assert [p["asked_hz"] for p in periodic] == [10.0, 100.0, 1000.0]
    for p in periodic:  # the rate field is a scaled u16: 0..1092 Hz in 65535 steps
        assert p["reports"] >= 2 and p["confirmed_hz"] == pytest.approx(p["asked_hz"], abs=0.02)
    change = doc["reports"]["every_change"]
    assert 0 < change["reports"] <= change["changes"]
    assert "paper 000 test 6" in stdout

    results = {"machine": bench.machine(quick=True), "skipped": {}, "failed": {},
               "jaus_paper000": doc}  # fmt: skip
    results.update(bench.summary(results))
    assert results["jaus_one_way_ms"]["paper_000_test_6"] == 0.270172
    assert results["jaus_one_way_ms"]["ups_can"] == doc["paths"]["ups_can"]["one_way_ms"]["mean"]
    text = _report.markdown(results, [])
    assert "## Paper 000's Table 2 beside this machine" in text
    assert "benchmarks/jaus_paper000.py" in text
