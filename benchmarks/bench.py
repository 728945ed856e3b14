"""``ups bench``: every figure of the paper's section 6 and of UPS's peers, in one run.

Each part is one of the benchmarks beside this module, run as its own process with ``--json``
(as a user would run it alone); this harness collects their figures, takes the ratios, and
writes one JSON document and, with ``--report DIR``, a report with plots. Parts that need CAN
across processes (``udp_multicast``) run inside a private network namespace through
``scripts/netns-run``. As root that is all; not as root, they run in an unprivileged user
namespace when the kernel allows one (``unshare --user --map-root-user``: the same private
network namespace, minus the second namespace pair of the two-host round trip, which needs
``ip netns add``), and are skipped otherwise; the output says which.

    ups bench [--quick] [--json PATH] [--report DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib.util
import json
import os
import platform
import shutil
import signal
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


def _run_json(
    module: str,
    args: list[str],
    timeout: float,
    netns: list[str] | None = None,
    tolerate_exit: bool = False,
) -> Any:
    """Run ``python -m ups.benchmarks.MODULE ARGS --json TMP`` (behind the ``netns`` prefix, if
    given) and return what it wrote; its output goes to our stderr's summary line. With
    ``tolerate_exit``, a non-zero exit that still wrote its JSON is the caller's to judge (a
    peer that failed is not UPS failing)."""
    with tempfile.TemporaryDirectory(prefix="ups-bench-") as tmp:
        out = Path(tmp) / "out.json"
        cmd = [*(netns or []), sys.executable, "-m", f"benchmarks.{module}", *args]
        cmd += ["--json", str(out)]
        started = time.monotonic()
        returncode, output = _run_part(cmd, timeout, module)
        print(f"  {module}: {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)
        if not out.exists() or (returncode != 0 and not tolerate_exit):
            raise Failed(f"{module} exited {returncode}:\n{output[-3000:]}")
        return json.loads(out.read_text())


def _run_part(cmd: list[str], timeout: float, name: str) -> tuple[int, str]:
    """Run ``cmd`` in a session of its own; after ``timeout`` seconds end it and every process
    it started (its process group, by the id of the child started here), and say so."""
    proc = subprocess.Popen(
        cmd,
        cwd=ROOT,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        output, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        for sig, grace in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
            try:
                output, _ = proc.communicate(timeout=grace)
                break
            except subprocess.TimeoutExpired:
                continue
        else:
            output = ""
        raise Failed(f"{name} timed out after {timeout:.0f} s:\n{output[-3000:]}") from None
    return proc.returncode, output


def namespace() -> tuple[list[str] | None, str]:
    """The command prefix that runs a part in a private network namespace (None: impossible
    here), and what the output should say about it ("" as root)."""
    if not NETNS_RUN.exists() or shutil.which("ip") is None or shutil.which("unshare") is None:
        return None, "needs scripts/netns-run, unshare and iproute2 (a checkout of the repository)"
    if os.geteuid() == 0:
        return [str(NETNS_RUN)], ""
    user_ns = ["unshare", "--user", "--map-root-user", "--"]
    probe = subprocess.run(
        [*user_ns, "unshare", "--net", "true"], capture_output=True, timeout=10, check=False
    )
    if probe.returncode == 0:
        return [*user_ns, str(NETNS_RUN)], (
            "not root: CAN parts ran in an unprivileged user namespace; the two-host round trip "
            "(ip netns add, veth) needs root and was skipped"
        )
    return None, "needs root or unprivileged user namespaces (CAN runs in a private namespace)"


# --- the parts -------------------------------------------------------------------------------


def _limit(quick: bool) -> float:
    """Seconds a part may take before it is ended (it takes a fraction of that)."""
    return 150.0 if quick else 600.0


def peers(quick: bool) -> dict[str, Any]:
    """Round trip and one-way throughput of UPS and its peers, 8-byte payloads, loopback.
    A peer that fails is shown as failed; UPS failing fails the part."""
    args = [
        "--roundtrips",
        "10000" if quick else "50000",
        "--warmup",
        "1000" if quick else "5000",
        "--messages",
        "200000" if quick else "500000",
    ]
    doc = _run_json("tcp_compare", args, _limit(quick), tolerate_exit=True)
    rows = {row["peer"]: row for row in doc["rows"]}
    broken = [
        f"{label}: {row['error']}"
        for label, row in rows.items()
        if label.startswith("UPS") and row["error"] and not row["error"].startswith("skipped")
    ]
    if broken or not any(label.startswith("UPS") and not r["error"] for label, r in rows.items()):
        raise Failed("UPS in tcp_compare: " + ("; ".join(broken) or "no UPS row measured"))
    return {"rows": rows, "environment": doc["environment"]}


def payload(quick: bool) -> list[dict[str, Any]]:
    """One-way throughput by payload size, UPS against raw TCP."""
    sizes = "8,1024,1048576" if quick else "8,64,1024,65536,1048576"
    result: list[dict[str, Any]] = _run_json(
        "tcp_payload", ["--sizes", sizes, "--mib", "128" if quick else "512"], _limit(quick)
    )
    return result


def fanout(quick: bool) -> list[dict[str, Any]]:
    """Lossless fan-out to 1..32 subscriber processes, UPS against pyzmq."""
    args = [
        "--subscribers",
        "1,4,16" if quick else "1,2,4,8,16,32",
        "--messages",
        "50000" if quick else "100000",
    ]
    result: list[dict[str, Any]] = _run_json("fanout", args, _limit(quick))
    return result


def zenoh(quick: bool) -> dict[str, Any]:
    """UPS's Zenoh face beside raw zenoh and UPS TCP: round trip, lossless one way, and the
    gateway's CAN -> Zenoh rate (a virtual bus: no namespace needed). Raw zenoh failing is
    shown as failed; UPS failing, or running out of time, fails the part."""
    limit = _limit(quick)
    args = ["--time-limit", f"{limit - 30:.0f}", *(["--quick"] if quick else [])]
    doc: dict[str, Any] = _run_json("zenoh_face", args, limit, tolerate_exit=True)
    broken = [
        f"{part}: {why.splitlines()[0]}"
        for part, why in doc["errors"].items()
        if "UPS" in part or part.startswith("gateway") or part == "time limit"
    ]
    if broken:
        raise Failed("zenoh_face: " + "; ".join(broken))
    return doc


def table5(quick: bool, netns: list[str], as_root: bool) -> dict[str, Any]:
    """The paper's Table 5 round trips (pinned) and the gateway's CAN->TCP rate."""
    args = ["--pin", "on"]
    if quick:
        args += ["--roundtrips", "1000", "--warmup", "100", "--events", "10000"]
        args += ["--rates", "7600,13000,20000,30000,50000,0", "--flat-events", "20000"]
        args += ["--pacing", "timer"]
    if not as_root:
        args.append("--no-veth")
    result: dict[str, Any] = _run_json("table5", args, _limit(quick), netns=netns)
    return result


def can_latency(quick: bool, netns: list[str]) -> dict[str, Any]:
    """Tables 3 and 4: local notification of 1..4 subscribers, publish -> frame on the bus."""
    args = ["--count", "500" if quick else "1000"]
    result: dict[str, Any] = _run_json("can_local_latency", args, _limit(quick), netns=netns)
    return result


def jaus(quick: bool, netns: list[str]) -> dict[str, Any]:
    """Paper 000's Table 2: minimal JAUS messages through ``ups jaus``, directly and by way of a
    UPS CAN node, beside the UPS CAN path; and JAUS reports per second."""
    args = ["--messages", "300" if quick else "1000", "--warmup", "30" if quick else "100"]
    args += ["--report-seconds", "2" if quick else "5"]
    result: dict[str, Any] = _run_json("jaus_paper000", args, _limit(quick), netns=netns)
    return result


def ethercat(quick: bool, netns: list[str]) -> dict[str, Any]:
    """Paper 000's EtherCAT side: ``ups ethercat``'s cycle beside a bare pysoem loop, and the
    paths EtherCAT -> UPS CAN, UPS CAN -> EtherCAT, JAUS -> UPS -> EtherCAT."""
    args = ["--seconds", "10" if quick else "60", "--messages", "100" if quick else "300"]
    result: dict[str, Any] = _run_json("ethercat", args, _limit(quick), netns=netns)
    return result


def startup(quick: bool) -> dict[str, float]:
    """``ups --help`` against ``python -c pass``: medians of fresh interpreters, alternated."""
    runs = 11 if quick else 21
    script = Path(sys.executable).with_name("ups")  # what a user types
    ups = [str(script), "--help"] if script.exists() else [sys.executable, "-m", "upscli", "-h"]
    from ups.benchmarks._procs import wall_time  # waits without polling

    times: dict[str, list[float]] = {"bare": [], "ups": []}
    for _ in range(runs):
        for key, cmd in (("bare", [sys.executable, "-c", "pass"]), ("ups", ups)):
            times[key].append(wall_time(cmd))
    bare, help_ = statistics.median(times["bare"]), statistics.median(times["ups"])
    return {"python_c_pass": bare, "ups_help": help_, "ratio": help_ / bare, "runs": runs}


def rss() -> dict[str, float]:
    """Resident memory (MB) of each daemon and of an idle TCP node, once started."""
    from ups.benchmarks._daemons import daemon_rss

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
    prefix, netns_note = namespace()
    if netns_note and prefix:
        results["notes"] = [netns_note]
        results["skipped"]["tcp_two_hosts"] = "needs root (ip netns add, a veth pair)"
    why_not_can = None if prefix else netns_note
    why_not_zenoh = None if importlib.util.find_spec("zenoh") else "eclipse-zenoh is not installed"
    why_not_ecat = None
    if os.geteuid() != 0 or importlib.util.find_spec("pysoem") is None:
        why_not_ecat = "needs root (a veth pair, raw sockets) and pysoem (the ethercat extra)"
    elif not (ROOT / "tests" / "ecat").is_dir():
        why_not_ecat = "needs the tests' EtherCAT slave emulator: run from a checkout"
    ns = prefix or []
    as_root = os.geteuid() == 0
    parts: list[tuple[str, Callable[[], Any], str | None]] = [
        ("startup_s", lambda: startup(quick), None),
        ("rss_mb", rss, None),
        ("code_size", code_size, None),
        ("tcp_compare", lambda: peers(quick), None),
        ("payload", lambda: payload(quick), None),
        ("fanout", lambda: fanout(quick), None),
        ("zenoh_face", lambda: zenoh(quick), why_not_zenoh),
        ("table5", lambda: table5(quick, ns, as_root), why_not_can),
        ("can_latency", lambda: can_latency(quick, ns), why_not_can),
        ("jaus_paper000", lambda: jaus(quick, ns), why_not_can),
        ("ethercat", lambda: ethercat(quick, ns), why_not_can or why_not_ecat),
    ]
    for key, part, why_not in parts:
        if why_not:
            results["skipped"][key] = why_not
            print(f"  {key}: skipped ({why_not})", file=sys.stderr)
            continue
        try:
            results[key] = part()
        except (Failed, subprocess.SubprocessError, OSError, RuntimeError, ValueError) as exc:
            results["failed"][key] = f"{type(exc).__name__}: {exc}"
            print(f"  {key}: FAILED: {exc}", file=sys.stderr)
    results.update(summary(results))
    return results


def machine(quick: bool) -> dict[str, Any]:
    """The machine, the interpreter and the versions of what is measured."""
    import importlib.metadata

    cpu = "unknown"
    with open("/proc/cpuinfo") as info:
        for line in info:
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    versions: dict[str, str | None] = {}
    for dist in ("ups-pubsub", "python-can", "msgpack", "uvloop", "pyzmq", "paho-mqtt",
                 "eclipse-zenoh", "matplotlib"):  # fmt: skip
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[dist] = None
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "cpu": cpu,
        "cpus": os.cpu_count(),
        "kernel": platform.release(),
        "python": sys.version.split()[0],
        "packages": versions,
        "mosquitto": _mosquitto_version(),
        "root": os.geteuid() == 0,
        "quick": quick,
    }


def _mosquitto_version() -> str | None:
    binary = shutil.which("mosquitto") or shutil.which("mosquitto", path="/usr/sbin:/sbin")
    if binary is None:
        return None
    done = subprocess.run([binary, "-h"], capture_output=True, text=True, timeout=10, check=False)
    first = (done.stdout or done.stderr).splitlines()
    return first[0].removeprefix("mosquitto version ") if first else "?"


def _p50_p99(values: list[float]) -> dict[str, float]:
    us = sorted(values)
    return {"p50": statistics.median(us), "p99": us[min(len(us) - 1, int(len(us) * 0.99))]}


def summary(r: dict[str, Any]) -> dict[str, Any]:
    """The keys every consumer of the JSON can count on (null or empty where a part did not
    run), the floors measured beside them, and the project's targets."""
    from ups.benchmarks import _report

    out: dict[str, Any] = {
        "local_notify_us": None,
        "publish_latency_us": None,
        "rtt_us": {},
        "throughput_msgs_per_s": {},
        "peers": {},
        "floors": {},
    }
    if "can_latency" in r:
        can = r["can_latency"]
        out["local_notify_us"] = {n: v["p50"] for n, v in can["local_notify_us"].items()}
        out["publish_latency_us"] = can["publish_latency_us"]["p50"]
        out["floors"]["python_can_recv_us"] = can["floor_us"]["p50"]
    if "table5" in r:
        keys = {
            "tcp_local": "tcp_same_host",
            "tcp_veth": "tcp_two_hosts",
            "tcp_gw_can": "tcp_gateway_can",
            "can_gw_tcp": "can_gateway_tcp",
            "can_can": "can_can",
        }
        floors = {"raw_tcp": "raw_tcp_rtt_us", "raw_can": "raw_can_rtt_us"}
        for row in r["table5"]["round_trips"]:
            if row["rtt_us"] and row["key"] in keys:
                out["rtt_us"][keys[row["key"]]] = _p50_p99(row["rtt_us"])
            elif row["rtt_us"] and row["key"] in floors:
                out["floors"][floors[row["key"]]] = _p50_p99(row["rtt_us"])
        lossless = [s["recv_rate"] for s in r["table5"]["rate"] if not s["lost"]]
        best = max(lossless, default=None)
        out["throughput_msgs_per_s"]["gateway_can_to_tcp"] = best
        out["throughput_msgs_per_s"]["saturated_1mbit_bus"] = BUS_8_BYTE_FRAMES
    if "tcp_compare" in r:
        rows = r["tcp_compare"]["rows"]
        ups = rows.get(UPS_ROW) or rows.get(UPS_ROW_STDLIB) or {}
        if ups.get("rate_msg_s") and not ups.get("lost"):
            out["throughput_msgs_per_s"]["tcp"] = ups["rate_msg_s"]
        if ups.get("rtt_p50_us"):  # table5's same-host path, when it ran, comes first
            out["rtt_us"].setdefault(
                "tcp_same_host", {"p50": ups["rtt_p50_us"], "p99": ups["rtt_p99_us"]}
            )
        for key, label in PEER_KEYS.items():
            row = rows.get(label, {})
            out["peers"][key] = {
                "rtt_p50_us": row.get("rtt_p50_us"),
                "rtt_p99_us": row.get("rtt_p99_us"),
                "throughput_msgs_per_s": row.get("rate_msg_s"),
                "lost": row.get("lost"),
                "error": row.get("error") or None,
            }
    if "zenoh_face" in r:
        out["zenoh"] = _zenoh_summary(r["zenoh_face"])
        out["throughput_msgs_per_s"]["zenoh"] = out["zenoh"]["throughput_msgs_per_s"]
        out["throughput_msgs_per_s"]["gateway_can_to_zenoh"] = out["zenoh"]["gateway_can_to_zenoh"]
    if "ethercat" in r:  # beside the part's own results, never over them
        e = r["ethercat"]
        out["ethercat_summary"] = {
            "late_percent": {k: e["cycle"][k]["late_percent"] for k in ("ups", "pysoem")},
            "lost": {k: e["cycle"][k]["lost"] for k in ("ups", "pysoem")},
            "one_way_ms": {
                k: (row["one_way_ms"] or {}).get("mean") for k, row in e["paths"].items()
            },
        }
    if "jaus_paper000" in r:
        out["jaus_one_way_ms"] = {
            key: (row["one_way_ms"] or {}).get("mean")
            for key, row in r["jaus_paper000"]["paths"].items()
        }
        out["jaus_one_way_ms"]["paper_000_test_6"] = r["jaus_paper000"]["paper_table2_ms"]["6"][
            "mean"
        ]
    out["targets"] = [
        {"target": name, "measured": value, "against": against, "met": met}
        for name, value, against, met in _report.targets({**r, **out})
    ]
    return out


def _zenoh_summary(doc: dict[str, Any]) -> dict[str, Any]:
    """The Zenoh face's figures (None where not measured, or where the gateway lost events),
    and each over raw zenoh's and over UPS TCP's (``ratios``)."""
    from ups.benchmarks.zenoh_face import GW_ZENOH, UPS_ZENOH

    rtt = doc["rtt"].get(UPS_ZENOH) or {}
    gw = doc["gateway"].get(GW_ZENOH) or {}
    return {
        "rtt_us": {"p50": rtt["p50_us"], "p99": rtt["p99_us"]} if rtt else None,
        "throughput_msgs_per_s": (doc["one_way"].get(UPS_ZENOH) or {}).get("rate"),
        "gateway_can_to_zenoh": gw.get("rate") if gw and not gw["lost"] else None,
        "ratios": doc.get("ratios", {}),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ups bench", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples (1-2 minutes here)")
    parser.add_argument("--json", metavar="PATH", help="write every figure as JSON here")
    parser.add_argument("--report", metavar="DIR", help="write report.md, results.json, plots")
    args = parser.parse_args(argv)
    from ups.benchmarks import _report

    missing = _report.missing_peers()
    if missing:
        from ups._extras import install_hint

        print(
            f"ups bench: {', '.join(missing)} not installed, skipped: {install_hint('bench')} "
            "(in a checkout, scripts/bench-setup installs them all, mosquitto too)",
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
        print(f"report: {Path(args.report) / 'report.md'}", file=sys.stderr)
    return 1 if results["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
