"""127 nodes, four processes, one bus, powered up in the same instant: every node gets a TxNode
of its own, and the frames on the bus grow linearly (benchmarks/join_storm.py, as processes
over udp_multicast in a private network namespace). Every node is given the bus spec, as an
application writes it, so the nodes of one process share one connection; with random ids and
with sequential ones (0x5000 + i). How fast is the benchmark's business."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from .procs import ROOT, private_multicast_bus

pytestmark = pytest.mark.netns


@pytest.mark.parametrize("ids", ["random", "sequential"])
def test_a_full_bus_of_simultaneous_joiners_all_get_distinct_txnodes(
    tmp_path: Path, ids: str
) -> None:
    bus = private_multicast_bus()
    out = tmp_path / "storm.json"
    cmd = [sys.executable, "-m", "ups.benchmarks.join_storm", "--nodes", "127", "--repeat", "1",
           "--timeout", "45", "--ids", ids, "--can", bus, "--json", str(out)]  # fmt: skip
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    (run,) = json.loads(out.read_text())["runs"]
    assert run["joined"] == 127 and run["distinct_txnodes"], run
    assert {node["txnode"] for node in run["nodes"]} == set(range(127))
    assert run["frames_per_join"] < 100, run  # linear: a few dozen frames each, whatever N
    assert not run["problems"], run
