"""UPS's Zenoh face beside raw zenoh and beside UPS on TCP/IP, in one run, on loopback, 8 B.

1. Round trip (p50, p99; ping-pong, warm-up first, every process pinned to ``--cpu`` as in
   ``tcp_compare``): two UPS nodes on their Zenoh face, in two processes, through one
   ``ups zenoh-router`` process; two plain zenoh client sessions through the same kind of
   router (a publisher and a subscriber each way, as the face sets them: reliable,
   congestion control DROP); and UPS over TCP/IP (``benchmarks/peers/ups_tcp``, uvloop).
2. One way, lossless: the highest rate at which the subscriber receives every event. A
   source sends ``--messages`` events flat out, then, if any was lost, at paced rates
   (1 ms ticks) below what the subscriber took, down until none is lost and back up between
   the best lossless and the lowest lossy rate. Zenoh publishers drop what they cannot send
   (DROP, as the face's): raw zenoh is searched the same way; raw zenoh with congestion
   control BLOCK and UPS TCP (backpressure) lose nothing flat out, which is their figure.
3. The gateway's CAN -> IP rate against a saturated bus: a ``Gateway`` on a python-can
   ``virtual`` bus in one process, a CAN node binds a channel and leaves, a raw python-can
   bus in the same process sends ``--gateway-events`` frames of that channel as fast as it
   can, all of them before the gateway reads any (it holds the interpreter meanwhile: the
   blaster's CPU is not the gateway's); a UPS subscriber process counts what the gateway
   forwards, to Zenoh (through a router) and to TCP (through a TCP-ECB), ``--gateway-runs``
   times (the median run's rate is the figure). The floor: a thread that reads the same bus
   and puts each frame's data on the channel's key, plain zenoh, no UPS.

Every figure is also given as a ratio: UPS Zenoh over raw zenoh, and over UPS TCP. Every
child is spawned here, every wait bounded, the whole run limited to ``--time-limit`` seconds;
every process is stopped by its PID on the way out.

    .venv/bin/python -m ups.benchmarks.zenoh_face [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import signal
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

from ups.benchmarks import _zenoh_rtt as rtt_roles
from ups.benchmarks import _zenoh_steps as step_roles
from ups.benchmarks import tcp_compare
from ups.benchmarks._procs import Spawned, free_port, process
from ups.benchmarks._zenoh_clients import REPORT_LIMIT
from ups.benchmarks.peers import PEERS, Link, PeerSpec

HOST = "127.0.0.1"
BUS = 7634  # a saturated 1 Mbit/s classic bus, 8-byte extended frames, no stuffing
UPS_ZENOH, RAW, RAW_BLOCK, UPS_TCP = ("UPS Zenoh face", "raw zenoh", "raw zenoh, BLOCK",
                                      "UPS TCP, uvloop")  # fmt: skip
GW_ZENOH, GW_TCP, GW_FLOOR = "gateway -> Zenoh", "gateway -> TCP", "python-can -> zenoh put"
OPTIONS = {UPS_ZENOH: {"kind": "ups"}, RAW: {"kind": "raw"},
           RAW_BLOCK: {"kind": "raw", "congestion": "block"}}  # fmt: skip
WAIT = 60.0  # for a child's answer to one command


@contextlib.contextmanager
def children(*specs: tuple[str, dict[str, Any]]) -> Iterator[list[Spawned]]:
    """Step roles (``_zenoh_steps.step_main``) started one after the other (each ready before
    the next), asked to quit after, and killed by PID if they have not after 5 s."""
    started: list[Spawned] = []
    try:
        for role, cfg in specs:
            started.append(Spawned(step_roles.step_main, (role, cfg), role))
            started[-1].expect("ready", WAIT)
        yield started
    finally:
        for child in reversed(started):
            child.send(("quit",))
            child.stop(5.0)


@contextlib.contextmanager
def router() -> Iterator[str]:
    """A ``ups zenoh-router`` process on a free port; its endpoint."""
    endpoint = f"tcp/{HOST}:{free_port()}"
    with process([sys.executable, "-m", "upscli", "zenoh-router", "--listen", endpoint],
                 "Zenoh router"):  # fmt: skip
        yield endpoint


@contextlib.contextmanager
def tcp_ecb() -> Iterator[str]:
    """A TCP-ECB process on a free port; its address."""
    address = f"{HOST}:{free_port()}"
    cmd = [sys.executable, "-m", "upscli", "broker", "--listen", address, "--recovery", "0"]
    with process(cmd, "TCP-ECB on"):
        yield address


# --- 1. round trips --------------------------------------------------------------------------


def round_trip(label: str, args: argparse.Namespace) -> dict[str, Any]:
    spec = PeerSpec(label, rtt_roles.__name__, OPTIONS[label])
    started = time.monotonic()
    times = tcp_compare.measure_rtt(spec, rtt_roles, args, args.roundtrips, args.warmup)
    rtts = sorted(t * 1e6 for t in times)
    pct = tcp_compare.percentile
    return {"p50_us": pct(rtts, 0.5), "p99_us": pct(rtts, 0.99),
            "roundtrips": len(rtts), "note": rtt_roles.describe(Link(HOST, (0,), OPTIONS[label])),
            "seconds": round(time.monotonic() - started, 1)}  # fmt: skip


def ups_tcp(args: argparse.Namespace) -> tuple[dict[str, Any], dict[str, Any]]:
    """UPS TCP's round trip and flat-out one way (backpressure: lossless), by tcp_compare."""
    row = tcp_compare.run_spec(PEERS["ups"][0], args)
    if row.error:
        raise RuntimeError(row.error)
    rtt = {"p50_us": row.rtt_p50_us, "p99_us": row.rtt_p99_us, "roundtrips": row.roundtrips,
           "note": row.note}  # fmt: skip
    one_way = {"rate": row.rate_msg_s if not row.lost else None, "flat_out": row.rate_msg_s,
               "lost": row.lost, "sent": row.sent, "received": row.received,
               "note": "flat out, publish_nowait, the sink's queue holds them all"}  # fmt: skip
    return rtt, one_way


# --- 2. one way, lossless ----------------------------------------------------------------------


def one_way(label: str, args: argparse.Namespace) -> dict[str, Any]:
    """The highest rate (``rate``) at which the sink got every one of ``args.messages``."""
    cfg = {**OPTIONS[label]}
    steps: list[dict[str, Any]] = []
    with router() as endpoint:
        cfg["endpoint"] = endpoint
        with children(("sink", cfg), ("source", cfg)) as (sink, source):
            prev: dict[str, int] = {}

            def step(rate: float, count: int = args.messages, keep: bool = True) -> dict[str, Any]:
                nonlocal prev
                n = len(steps) + 1 if keep else 0
                done = source.ask(("run", n, rate, count), "done", WAIT + count / 1000)
                got = sink.ask(("report", n, count), "result", REPORT_LIMIT + 5)
                stats, was = got["stats"], prev
                out = {"asked": rate, "sent": count, "send_rate": count / done["seconds"],
                       "received": got["received"], "lost": count - got["received"],
                       "rate": (got["received"] - 1) / got["seconds"] if got["seconds"] else 0.0,
                       "counted_lost": stats.get("lost", 0) - was.get("lost", 0),
                       "rx_overflow": stats.get("rx_overflow", 0) - was.get("rx_overflow", 0),
                       }  # fmt: skip
                prev = stats
                if keep:
                    steps.append(out)
                time.sleep(0.2)  # let anything late arrive before the next step
                return out

            step(20_000, min(args.messages, 4000), keep=False)  # warm-up: not reported
            flat = step(0)
            if flat["lost"] and label != RAW_BLOCK:
                search(step, flat, args.refine)
    best = max((s["rate"] for s in steps if not s["lost"]), default=None)
    counted = None if cfg["kind"] == "raw" else flat["counted_lost"] + flat["rx_overflow"]
    return {"rate": best, "flat_out": flat["rate"], "lost": flat["lost"],
            "counted_lost": counted, "steps": steps,
            "note": rtt_roles.describe(Link(HOST, (0,), OPTIONS[label]))}  # fmt: skip


def search(step: Any, flat: dict[str, Any], refine: int) -> None:
    """Paced steps: from 0.9x what the sink took flat out, down by 0.7x until none is lost
    (4 tries at most); then ``refine`` times halfway (geometrically) between the best
    lossless and the lowest lossy rate."""
    rate, lossy, good = 0.9 * flat["rate"], flat["send_rate"], 0.0
    for _ in range(4):
        if not step(rate)["lost"]:
            good = rate
            break
        lossy, rate = rate, rate * 0.7
    for _ in range(refine if good else 0):
        rate = math.sqrt(good * lossy)
        if step(rate)["lost"]:
            lossy = rate
        else:
            good = rate


# --- 3. the gateway --------------------------------------------------------------------------


def gateway(ip: str, events: int, runs: int, tmp: Path) -> dict[str, Any]:
    """``runs`` times ``events`` frames blasted onto the gateway's bus: what the subscriber
    got, how fast (``rate``: the median run's)."""
    infra = tcp_ecb() if ip == "tcp" else router()
    with infra as endpoint:
        sink_cfg = {"kind": "tcp" if ip == "tcp" else "ups", "endpoint": endpoint}
        gw_cfg = {"ip": ip, "endpoint": endpoint, "bus": f"zbench-{ip}-{tmp.name}",
                  "db": str(tmp / f"gw-{ip}.db")}  # fmt: skip
        with children(("sink", sink_cfg), ("gateway", gw_cfg)) as (sink, gw):
            done = [blast_once(sink, gw, n, events, ip) for n in range(1, runs + 1)]
    lost = sum(r["lost"] for r in done)
    return {"rate": statistics.median(r["rate"] for r in done), "sent": events * runs,
            "received": sum(r["received"] for r in done), "lost": lost,
            "counted_lost": None if ip == "bridge" else done[-1]["counted_lost"],  # no numbers
            "runs": done}  # fmt: skip


def blast_once(sink: Spawned, gw: Spawned, step: int, events: int, ip: str) -> dict[str, Any]:
    key = "to_tcp" if ip == "tcp" else "to_zenoh"
    before = gw.ask(("stats",), "stats")
    blast = gw.ask(("blast", step, events), "done", WAIT + events / 1000)
    got = sink.ask(("report", step, events), "result", REPORT_LIMIT + 5)
    after, stats = gw.ask(("stats",), "stats"), got["stats"]
    time.sleep(0.2)
    return {
        "rate": (got["received"] - 1) / got["seconds"] if got["seconds"] else 0.0,
        "blast_rate": events / blast["seconds"], "received": got["received"],
        "lost": events - got["received"], "forwarded": after.get(key, 0) - before.get(key, 0),
        "counted_lost": stats.get("lost", 0), "rx_overflow": stats.get("rx_overflow", 0),
        "gateway_dropped": {k: after[k] - before.get(k, 0) for k in after
                            if k.endswith(("_dropped", "_lost", "tx_failed")) and after[k]},
        # > 0: the gateway forwarded nothing before the whole blast was on the bus
        "first_after_blast_s": got["first"] - blast["end"],
        "cpu_pct": 100 * (after["cpu_s"] - blast["cpu_s"]) / max(got["seconds"], 1e-9),
    }  # fmt: skip


# --- the run -----------------------------------------------------------------------------------


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def ratios(doc: dict[str, Any]) -> dict[str, dict[str, float | None]]:
    """Each UPS Zenoh figure over raw zenoh's and over UPS TCP's."""
    rtt, ow, gw = doc["rtt"], doc["one_way"], doc["gateway"]

    def of(table: dict[str, Any], label: str, key: str) -> float | None:
        return (table.get(label) or {}).get(key)

    out: dict[str, dict[str, float | None]] = {}
    for key in ("p50_us", "p99_us"):
        z = of(rtt, UPS_ZENOH, key)
        out[f"rtt_{key}"] = {"vs_raw_zenoh": _ratio(z, of(rtt, RAW, key)),
                             "vs_ups_tcp": _ratio(z, of(rtt, UPS_TCP, key))}  # fmt: skip
    z = of(ow, UPS_ZENOH, "rate")
    out["one_way_rate"] = {"vs_raw_zenoh": _ratio(z, of(ow, RAW, "rate")),
                           "vs_ups_tcp": _ratio(z, of(ow, UPS_TCP, "rate"))}  # fmt: skip
    z = of(gw, GW_ZENOH, "rate")
    out["gateway_rate"] = {"vs_raw_zenoh": _ratio(z, of(gw, GW_FLOOR, "rate")),
                           "vs_ups_tcp": _ratio(z, of(gw, GW_TCP, "rate"))}  # fmt: skip
    return out


def measure(args: argparse.Namespace, doc: dict[str, Any]) -> None:
    """Every part, into ``doc`` (its settings and empty tables); one that fails is recorded in
    ``errors``, the rest go on."""

    def part(name: str, fn: Any) -> None:
        started = time.monotonic()
        try:
            fn()
            status = "ok"
        except Exception as exc:
            doc["errors"][name] = f"{type(exc).__name__}: {exc}"
            status = f"FAILED: {doc['errors'][name].splitlines()[0]}"
        print(f"  {name}: {status} ({time.monotonic() - started:.1f} s)", flush=True)

    def tcp() -> None:
        doc["rtt"][UPS_TCP], doc["one_way"][UPS_TCP] = ups_tcp(args)

    for label in (UPS_ZENOH, RAW):
        part(f"round trip, {label}", lambda label=label: doc["rtt"].__setitem__(
            label, round_trip(label, args)))  # fmt: skip
    part(f"round trip and one way, {UPS_TCP}", tcp)
    for label in (UPS_ZENOH, RAW, RAW_BLOCK):
        part(f"one way, {label}", lambda label=label: doc["one_way"].__setitem__(
            label, one_way(label, args)))  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="ups-bench-zgw-") as tmp:
        for label, ip in ((GW_ZENOH, "zenoh"), (GW_TCP, "tcp"), (GW_FLOOR, "bridge")):
            part(label, lambda label=label, ip=ip: doc["gateway"].__setitem__(
                label, gateway(ip, args.gateway_events, args.gateway_runs, Path(tmp))))  # fmt: skip
    doc["ratios"] = ratios(doc)


# --- output ------------------------------------------------------------------------------------


def _f(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _x(a: float | None, b: float | None) -> str:
    return _f(_ratio(a, b), ".2f") + ("x" if a and b else "")


def _lost(row: dict[str, Any] | None) -> str:
    if not row:
        return "-"
    counted = row.get("counted_lost")
    return f"{row['lost']}" + ("" if counted is None else f" ({counted})")


def summary(doc: dict[str, Any]) -> tuple[str, list[str], list[list[str]]]:
    """Every figure of UPS's Zenoh face beside raw zenoh's and UPS TCP's, and the ratios."""
    rtt, ow, gw = doc["rtt"], doc["one_way"], doc["gateway"]
    body = []
    for what, table, labels, key, spec in (
        ("round trip p50, µs", rtt, (UPS_ZENOH, RAW, UPS_TCP), "p50_us", ".1f"),
        ("round trip p99, µs", rtt, (UPS_ZENOH, RAW, UPS_TCP), "p99_us", ".1f"),
        ("one way, lossless, msg/s", ow, (UPS_ZENOH, RAW, UPS_TCP), "rate", ",.0f"),
        ("gateway CAN -> IP, events/s", gw, (GW_ZENOH, GW_FLOOR, GW_TCP), "rate", ",.0f"),
    ):
        z, raw, tcp = ((table.get(label) or {}).get(key) for label in labels)
        body.append([what, _f(z, spec), _f(raw, spec), _f(tcp, spec), _x(z, raw), _x(z, tcp)])
    for what, table, labels in (("one way flat out: lost", ow, (UPS_ZENOH, RAW, UPS_TCP)),
                                ("gateway: lost", gw, (GW_ZENOH, GW_FLOOR, GW_TCP))):  # fmt: skip
        body.append([f"{what} (UPS counted)", *(_lost(table.get(label)) for label in labels),
                     "", ""])  # fmt: skip
    return ("UPS Zenoh face against raw zenoh and UPS TCP, 8 B, loopback (gateway: raw = "
            "python-can -> zenoh put)", ["", "UPS Zenoh", "raw zenoh", "UPS TCP",
            "UPS Zenoh / raw zenoh", "UPS Zenoh / UPS TCP"], body)  # fmt: skip


def tables(doc: dict[str, Any]) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows): the summary, then the one-way steps and the gateway's runs."""
    out = [summary(doc)]
    body = [[label, _f(r.get("rate"), ",.0f"), _f(r.get("flat_out"), ",.0f"), str(r.get("lost")),
             " ".join(f"{s['asked'] / 1000:.0f}k:{s['lost'] or 'ok'}" for s in r["steps"][1:])
             if r.get("steps") else "-", r.get("note", "")]
            for label, r in doc["one_way"].items()]  # fmt: skip
    out.append((f"Zenoh face, one way, 8 B, {doc['settings']['messages']:,} events a step: flat "
                "out, then paced", ["", "msg/s, no loss", "flat out msg/s", "lost flat out",
                "paced (asked:lost)", ""], body))  # fmt: skip
    body = [[label, _f(r["rate"], ",.0f"), _x(r["rate"], BUS), f"{r['received']:,}/{r['sent']:,}",
             str(r["lost"]), _f(r["counted_lost"], "d"),
             " ".join(f"{run['rate'] / 1000:.0f}k" for run in r["runs"]),
             " ".join(f"{run['cpu_pct']:.0f}%" for run in r["runs"]),
             "yes" if all(run["first_after_blast_s"] > 0 for run in r["runs"]) else "NO"]
            for label, r in doc["gateway"].items()]  # fmt: skip
    out.append((f"Zenoh face, gateway CAN -> IP: {doc['settings']['gateway_events']:,} frames "
                "in the gateway's virtual bus, then drained",
                ["", "forwarded/s (median)", "x 1 Mbit/s bus", "received", "lost", "counted lost",
                 "runs", "CPU draining", "bus full first"], body))  # fmt: skip
    return out


def text(doc: dict[str, Any]) -> str:
    from ups.benchmarks._tables import aligned

    lines = aligned(tables(doc))
    lines += [f"FAILED {k}: {v.splitlines()[0]}" for k, v in doc["errors"].items()]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer samples (about 1 minute)")
    p.add_argument("--roundtrips", type=int, help="measured round trips (5000; quick 2000)")
    p.add_argument("--warmup", type=int, help="round trips before measuring (1000; quick 300)")
    p.add_argument("--messages", type=int, help="events a one-way step (300000; quick 100000)")
    p.add_argument("--gateway-events", type=int, help="frames blasted (100000; quick 30000)")
    p.add_argument("--gateway-runs", type=int, default=3, help="blasts at each gateway (3)")
    p.add_argument("--refine", type=int, help="steps between lossless and lossy (3; quick 2)")
    p.add_argument("--cpu", type=int, default=0, help="the CPU round trips are pinned to")
    p.add_argument("--time-limit", type=float, help="seconds before it gives up (600; quick 150)")
    p.add_argument("--json", metavar="PATH", help="also write the results as JSON here")
    p.set_defaults(pairs=1)  # tcp_compare's process pairs: one, for every round trip here
    args = p.parse_args(argv)
    defaults = {"roundtrips": (5000, 2000), "warmup": (1000, 300), "messages": (300_000, 100_000),
                "gateway_events": (100_000, 30_000), "refine": (3, 2),
                "time_limit": (600.0, 150.0)}  # fmt: skip
    for key, (full, quick) in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, quick if args.quick else full)
    if min(args.roundtrips, args.messages, args.gateway_events) < 2:
        p.error("--roundtrips, --messages and --gateway-events need at least 2")
    args.pin_throughput = False  # for tcp_compare: one way unpinned
    return args


class OutOfTime(BaseException):
    """The run's time limit passed (not an Exception: no part catches it)."""


def _out_of_time(signum: int, frame: FrameType | None) -> None:
    raise OutOfTime(f"time limit ({signum}) reached")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    print(f"loopback, 8-byte events: {args.roundtrips} round trips (+{args.warmup}) pinned to "
          f"CPU {args.cpu}; {args.messages} events a one-way step; {args.gateway_events} "
          f"frames blasted at the gateway; at most {args.time_limit:.0f} s")  # fmt: skip
    started = time.monotonic()
    signal.signal(signal.SIGALRM, _out_of_time)  # raised in whatever waits: every finally runs
    signal.setitimer(signal.ITIMER_REAL, args.time_limit)
    doc: dict[str, Any] = {"settings": {k: v for k, v in vars(args).items() if k != "json"},
                           "environment": tcp_compare.environment(), "rtt": {}, "one_way": {},
                           "gateway": {}, "errors": {}}  # fmt: skip
    try:
        measure(args, doc)
    except OutOfTime:
        doc["errors"]["time limit"] = f"gave up after {args.time_limit:.0f} s"
        doc["ratios"] = ratios(doc)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    doc["seconds"] = round(time.monotonic() - started, 1)
    print(f"\n{text(doc)}\ntotal {doc['seconds']:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=1))
    return 1 if doc["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
