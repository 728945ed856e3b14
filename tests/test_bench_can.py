"""``ups bench``'s CAN parts and its daemons' memory: a tiny real run of each goes through the
summary, the text the terminal shows and report.md whole, as ``ups bench`` puts them together
(issue 39: every part of the report runs in a test on that part's real output). Timings are
never asserted here (a benchmark, not a test); what is checked is that each figure arrives
where the report says it is, and that no part's output is lost or replaced on the way."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from ups.benchmarks import _report, bench

from .procs import private_multicast_bus

pytestmark = [pytest.mark.netns, pytest.mark.timeout(240)]


def _report_of(results: dict[str, Any], tmp_path: Path) -> tuple[str, str, dict[str, Any]]:
    """The terminal text, report.md and results.json of ``results``, as ``ups bench`` writes
    them (after the summary)."""
    results.update(bench.summary(results))
    _report.write(results, tmp_path / "report")
    md = (tmp_path / "report" / "report.md").read_text()
    doc = json.loads((tmp_path / "report" / "results.json").read_text())
    return _report.text(results), md, doc


def test_the_report_takes_table5s_and_can_latencys_real_output(tmp_path: Path) -> None:
    private_multicast_bus()  # udp_multicast across processes: only inside a private namespace
    netns: list[str] = []  # already inside one: the parts run here, as root in CI
    table5 = bench._run_json(
        "table5",
        ["--pin", "on", "--roundtrips", "40", "--warmup", "5", "--events", "300",
         "--rates", "2000,0", "--flat-events", "600", "--pacing", "timer"],
        200, netns=netns,
    )  # fmt: skip
    can = bench._run_json(
        "can_local_latency", ["--count", "40", "--rate", "1000", "--recovery", "0.2"], 120, netns
    )  # its own bus: no node before
    results = {"machine": bench.machine(quick=True), "skipped": {}, "failed": {},
               "table5": table5, "can_latency": can}  # fmt: skip
    text, md, doc = _report_of(results, tmp_path)
    assert results["table5"] is table5 and results["can_latency"] is can  # never replaced

    # every round trip that table5 measured is in the summary, under the name the report uses
    measured = {row["key"] for row in table5["round_trips"] if row["rtt_us"]}
    assert {"tcp_local", "tcp_gw_can", "can_gw_tcp", "can_can"} <= measured
    assert {"tcp_same_host", "tcp_gateway_can", "can_gateway_tcp", "can_can"} <= set(
        results["rtt_us"]
    )
    assert {"raw_tcp_rtt_us", "raw_can_rtt_us", "python_can_recv_us"} <= set(results["floors"])
    for key, label in _report.RTT_LABELS.items():
        if key in results["rtt_us"]:
            assert label in text and label in md
    # the gateway's rate: the best lossless step, as measured
    lossless = [s["recv_rate"] for s in table5["rate"] if not s["lost"]]
    assert results["throughput_msgs_per_s"]["gateway_can_to_tcp"] == max(lossless, default=None)

    # Tables 3 and 4: one row per number of local subscribers, and the publish latency
    assert set(results["local_notify_us"]) == {"1", "2", "3", "4"}
    assert results["publish_latency_us"] == can["publish_latency_us"]["p50"]
    assert "The paper's section 6 on this machine" in text
    assert "publish -> frame on the bus" in text and "Gateway CAN -> TCP" in md
    for n in ("1", "2", "3", "4"):
        assert f"local notification, {n} subscriber(s)" in text and f"{n} subscriber(s)" in md
    targets = {t["target"]: t for t in results["targets"]}
    assert all(t["met"] is None or isinstance(t["met"], bool) for t in targets.values())
    assert doc["table5"]["round_trips"] and doc["can_latency"]["local_notify_us"]
    assert doc["rtt_us"] == json.loads(json.dumps(results["rtt_us"]))


def test_the_report_takes_the_daemons_real_memory(tmp_path: Path) -> None:
    rss = bench.rss()
    assert set(rss) == {"python_bare", "tcp_ecb", "idle_tcp_node", "gateway", "can_ecb"}
    assert all(mb > 0 for mb in rss.values())
    results = {"machine": bench.machine(quick=True), "skipped": {}, "failed": {},
               "rss_mb": rss}  # fmt: skip
    text, md, _ = _report_of(results, tmp_path)
    for name in rss:
        assert name in text and name in md
