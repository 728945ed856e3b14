"""``ups bench``: every figure of the paper's section 6 and of UPS's peers, in one run.

Each part is one of the benchmarks beside this module, run as its own process with ``--json``
(as a user would run it alone); this harness collects their figures, takes the ratios, and
writes one JSON document and, with ``--report DIR``, a report with plots. Parts that need CAN
across processes (``udp_multicast``) run inside a private network namespace through
``scripts/netns-run``, so they need root; without it they are skipped, and said so.

    ups bench [--quick] [--json PATH] [--report DIR]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
NETNS_RUN = ROOT / "scripts" / "netns-run"
PEER_KEYS = {
    "raw_tcp": "raw TCP",
    "zmq": "pyzmq PUB/SUB, HWM=0",
    "mqtt": "paho-mqtt QoS 0 + mosquitto",
    "zenoh": "zenoh peer-to-peer",
}
UPS_ROW = "UPS TCP, uvloop"
UPS_ROW_STDLIB = "UPS TCP, stdlib loop"
BUS_8_BYTE_FRAMES = 7634  # a saturated 1 Mbit/s classic bus, 8-byte frames, no stuffing


class Failed(Exception):
    """A part of the run that measures UPS failed."""


def _run_json(module: str, args: list[str], timeout: float, netns: bool = False) -> Any:
    """Run ``python -m benchmarks.MODULE ARGS --json TMP`` (in a private namespace with
    ``netns``) and return what it wrote; its output goes to our stderr, for the record."""
    with tempfile.TemporaryDirectory(prefix="ups-bench-") as tmp:
        out = Path(tmp) / "out.json"
        cmd = [sys.executable, "-m", f"benchmarks.{module}", *args, "--json", str(out)]
        if netns:
            cmd = [str(NETNS_RUN), *cmd]
        started = time.monotonic()
        done = subprocess.run(
            cmd,
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=timeout,
        )
        print(f"  {module}: {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)
        if done.returncode != 0 or not out.exists():
            raise Failed(f"{module} exited {done.returncode}:\n{done.stdout[-3000:]}")
        return json.loads(out.read_text())


def _can_parts() -> str | None:
    """Why the CAN parts cannot run here, or None."""
    if os.geteuid() != 0:
        return "needs root: CAN across processes runs in a private network namespace"
    if not NETNS_RUN.exists() or shutil.which("ip") is None:
        return "needs scripts/netns-run and iproute2 (a checkout of the repository)"
    return None


# --- the parts -------------------------------------------------------------------------------


def peers(quick: bool) -> dict[str, Any]:
    """Round trip and one-way throughput of UPS and its peers, 8-byte payloads, loopback."""
    args = [
        "--roundtrips",
        "5000" if quick else "50000",
        "--warmup",
        "500" if quick else "5000",
        "--messages",
        "100000" if quick else "500000",
    ]
    doc = _run_json("tcp_compare", args, 600 if quick else 1200)
    rows = {row["peer"]: row for row in doc["rows"]}
    return {"rows": rows, "environment": doc["environment"]}


def payload(quick: bool) -> list[dict[str, Any]]:
    sizes = "8,1024,1048576" if quick else "8,64,1024,65536,1048576"
    result: list[dict[str, Any]] = _run_json(
        "tcp_payload", ["--sizes", sizes, "--mib", "128" if quick else "512"], 600
    )
    return result


def table5(quick: bool) -> dict[str, Any]:
    args = ["--pin", "on"]
    if quick:
        args += [
            "--roundtrips",
            "300",
            "--warmup",
            "30",
            "--rates",
            "7600,0",
            "--events",
            "10000",
            "--flat-events",
            "20000",
            "--pacing",
            "timer",
        ]
    result: dict[str, Any] = _run_json("table5", args, 600 if quick else 1200, netns=True)
    return result


def can_latency(quick: bool) -> dict[str, Any]:
    args = ["--count", "200" if quick else "500"]
    result: dict[str, Any] = _run_json("can_local_latency", args, 300, netns=True)
    return result


def startup(quick: bool) -> dict[str, float]:
    """``ups --help`` against ``python -c pass``: medians of fresh interpreters."""
    runs = 5 if quick else 15

    def median_s(cmd: list[str]) -> float:
        times = []
        for _ in range(runs):
            started = time.perf_counter()
            subprocess.run(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, check=True, timeout=30)
            times.append(time.perf_counter() - started)
        return statistics.median(times)

    bare = median_s([sys.executable, "-c", "pass"])
    script = Path(sys.executable).with_name("ups")  # what a user types
    ups = median_s(
        [str(script), "--help"] if script.exists() else [sys.executable, "-m", "ups.cli", "--help"]
    )
    return {"python_c_pass_s": bare, "ups_help_s": ups, "ratio": ups / bare}


def rss() -> dict[str, float]:
    """Resident memory (MB) of each daemon and of an idle TCP node, once started."""
    from benchmarks._daemons import daemon_rss

    return daemon_rss()


def code_size() -> dict[str, dict[str, int]]:
    """Table 6: the source of each component (the paper gives compiled KB)."""
    parts = {
        "ECH (ups, without tools and rt)": ["ups"],
        "ECB (broker)": ["broker"],
        "gateway": ["gateway"],
        "tools (ups/tools)": ["ups/tools"],
        "real-time analysis (ups/rt)": ["ups/rt"],
    }
    sizes = {}
    for label, dirs in parts.items():
        files = [f for d in dirs for f in (ROOT / d).rglob("*.py")]
        if label.startswith("ECH"):
            files = [f for f in files if not {"tools", "rt"} & set(f.relative_to(ROOT).parts)]
        sizes[label] = {
            "files": len(files),
            "lines": sum(len(f.read_text().splitlines()) for f in files),
            "kb": round(sum(f.stat().st_size for f in files) / 1024),
        }
    return sizes


# --- the run ---------------------------------------------------------------------------------


def run(quick: bool) -> dict[str, Any]:
    """Every part; a part that cannot run here is recorded as skipped (with why)."""
    results: dict[str, Any] = {"machine": machine(quick), "skipped": {}, "failed": {}}
    why_not_can = _can_parts()
    parts: list[tuple[str, Callable[[], Any], str | None]] = [
        ("startup", lambda: startup(quick), None),
        ("rss_mb", rss, None),
        ("code_size", code_size, None),
        ("tcp_compare", lambda: peers(quick), None),
        ("payload", lambda: payload(quick), None),
        ("fanout", lambda: _fanout(quick), None),
        ("table5", lambda: table5(quick), why_not_can),
        ("can_latency", lambda: can_latency(quick), why_not_can),
    ]
    for key, part, why_not in parts:
        if why_not:
            results["skipped"][key] = why_not
            print(f"  {key}: skipped ({why_not})", file=sys.stderr)
            continue
        try:
            results[key] = part()
        except (Failed, subprocess.TimeoutExpired, OSError) as exc:
            results["failed"][key] = str(exc)
            print(f"  {key}: FAILED: {exc}", file=sys.stderr)
    results.update(summary(results))
    return results


def _fanout(quick: bool) -> Any:
    args = [
        "--subscribers",
        "1,4,16" if quick else "1,2,4,8,16,32",
        "--messages",
        "20000" if quick else "100000",
    ]
    return _run_json("fanout", args, 900)


def machine(quick: bool) -> dict[str, Any]:
    cpu = "unknown"
    with open("/proc/cpuinfo") as info:
        for line in info:
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "cpu": cpu,
        "cpus": os.cpu_count(),
        "kernel": platform.release(),
        "python": sys.version.split()[0],
        "quick": quick,
    }


def summary(r: dict[str, Any]) -> dict[str, Any]:
    """The keys every consumer of the JSON can count on (null where a part did not run)."""
    out: dict[str, Any] = {
        "local_notify_us": None,
        "publish_latency_us": None,
        "rtt_us": {},
        "throughput_msgs_per_s": {},
        "peers": {},
    }
    if "can_latency" in r:
        out["local_notify_us"] = {
            n: v["p50"] for n, v in r["can_latency"]["local_notify_us"].items()
        }
        out["publish_latency_us"] = r["can_latency"]["publish_latency_us"]["p50"]
    if "table5" in r:
        keys = {
            "tcp_local": "tcp_same_host",
            "tcp_veth": "tcp_two_hosts",
            "tcp_gw_can": "tcp_gateway_can",
            "can_gw_tcp": "can_gateway_tcp",
        }
        for row in r["table5"]["round_trips"]:
            if row["key"] in keys and row["rtt_us"]:
                us = sorted(row["rtt_us"])
                out["rtt_us"][keys[row["key"]]] = {
                    "p50": statistics.median(us),
                    "p99": us[min(len(us) - 1, int(len(us) * 0.99))],
                }
        lossless = [s["recv_rate"] for s in r["table5"]["rate"] if not s["lost"]]
        out["throughput_msgs_per_s"]["gateway_can_to_tcp"] = max(lossless, default=None)
    if "tcp_compare" in r:
        rows = r["tcp_compare"]["rows"]
        ups = rows.get(UPS_ROW) or rows.get(UPS_ROW_STDLIB) or {}
        if ups.get("rate_msg_s") and not ups.get("lost"):
            out["throughput_msgs_per_s"]["tcp"] = ups["rate_msg_s"]
        if ups.get("rtt_p50_us"):  # same host, pinned (table5's path 1 is unpinned-free too)
            out["rtt_us"].setdefault(
                "tcp_same_host", {"p50": ups["rtt_p50_us"], "p99": ups["rtt_p99_us"]}
            )
        for key, label in PEER_KEYS.items():
            row = rows.get(label, {})
            out["peers"][key] = {
                "rtt_p50_us": row.get("rtt_p50_us"),
                "throughput_msgs_per_s": row.get("rate_msg_s"),
            }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ups bench", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples (about 4 minutes)")
    parser.add_argument("--json", metavar="PATH", help="write every figure as JSON here")
    parser.add_argument("--report", metavar="DIR", help="write report.md, results.json, plots")
    args = parser.parse_args(argv)
    from benchmarks import _report

    missing = _report.missing_peers()
    if missing:
        print(
            f"ups bench: {', '.join(missing)} not installed, skipped in the comparison: "
            "pip install 'ups-pubsub[bench]' (or scripts/bench-setup)",
            file=sys.stderr,
        )
    started = time.monotonic()
    results = run(args.quick)
    results["machine"]["seconds"] = round(time.monotonic() - started)
    print(_report.text(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
    if args.report:
        _report.write(results, Path(args.report))
    return 1 if results["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
