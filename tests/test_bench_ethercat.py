"""``benchmarks/ethercat``: a tiny real run's output goes through ``ups bench``'s summary and
report whole (the summary used to replace the part's results under the same key, and the
report then failed with ``KeyError: 'cycle'`` after every measurement). Timings are never
asserted here (a benchmark, not a test)."""

from __future__ import annotations

import pytest

from ups.benchmarks import _report, bench

from .procs import private_multicast_bus

pytestmark = [pytest.mark.netns, pytest.mark.timeout(180)]


def test_the_report_takes_the_ethercat_parts_real_output() -> None:
    private_multicast_bus()  # a veth pair and raw sockets: only inside a private namespace
    pytest.importorskip("pysoem", reason="the ethercat extra is not installed")
    doc = bench._run_json("ethercat", ["--seconds", "1", "--messages", "10", "--gap", "5"], 150)
    results = {"machine": bench.machine(quick=True), "skipped": {}, "failed": {},
               "ethercat": doc}  # fmt: skip
    results.update(bench.summary(results))
    assert results["ethercat"] is doc  # the part's own output, untouched
    assert set(results["ethercat_summary"]["late_percent"]) == {"ups", "pysoem"}
    text = _report.markdown(results, [])
    assert "EtherCAT cycle" in text and "bare pysoem loop" in text
