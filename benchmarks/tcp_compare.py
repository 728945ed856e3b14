"""Round trip and one-way throughput on loopback TCP, 8-byte payloads, several peers side by side.

For each selected peer (``benchmarks/peers/``), in one run:

* round trip: a pong process echoes, a ping process sends messages one at a time after a
  warm-up and times each; both are pinned to one CPU (``--cpu``), and so is a broker if the
  peer has one. ``--pairs`` pairs of processes, one after the other, each with N / pairs of
  the N round trips: a pair's figure depends on where its code landed in memory (address
  randomization; up to a third for UPS), so one pair alone is a draw. Reported: p50 and p99
  of all the pairs' round trips together in microseconds, each pair's p50, and p50 as a
  multiple of the raw-TCP floor.
* throughput: a source process sends M messages as fast as the transport takes them, a sink
  process counts what arrives. Reported: received/sent, loss, and the rate at the sink
  (messages between its first and last arrival). Unpinned unless ``--pin-throughput``.

Each side is a separate ``spawn``ed process; every wait has a timeout and every child is
killed by PID if it has not ended. Needs ``scripts/bench-setup`` for pyzmq, paho-mqtt,
eclipse-zenoh, uvloop and mosquitto; a peer whose package is missing is skipped.

    .venv/bin/python -m ups.benchmarks.tcp_compare [--roundtrips N] [--messages M]
        [--peers raw,asyncio,zmq,mqtt,zenoh,ups] [--json PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.metadata
import json
import os
import platform
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from types import ModuleType
from typing import Any

from ups.benchmarks._procs import Spawned, free_ports
from ups.benchmarks.peers import PEERS, Link, PeerSpec, SinkResult
from ups.benchmarks.peers._child import run_role

HOST = "127.0.0.1"
RAW_LABEL = PEERS["raw"][0].label  # the floor the ratios are taken against
IDLE_TIMEOUT = 2.0  # a sink gives up after this long without a message
SETUP_TIMEOUT = 30.0  # for a child to get ready, and slack added to every other wait
EXIT_GRACE = 5.0  # for a child to exit by itself before it is killed


@dataclass
class Row:
    """One line of the table (all times in microseconds, rates in messages per second)."""

    peer: str
    note: str = ""
    rtt_p50_us: float | None = None
    rtt_p99_us: float | None = None
    rtt_mean_us: float | None = None
    rtt_p50_x_raw: float | None = None
    roundtrips: int = 0
    rtt_p50_pairs_us: list[float] = field(default_factory=list)  # each process pair's p50
    sent: int = 0
    received: int = 0
    lost: int = 0
    rate_msg_s: float | None = None
    error: str = ""


def _role(
    spec: PeerSpec, role: str, link: Link, kwargs: dict[str, Any], pin: int | None
) -> Spawned:
    """One role of a peer in a spawned process (``run_<role>`` of its module)."""
    name = f"{spec.module.rsplit('.', 1)[-1]}:{role}"
    return Spawned(run_role, (spec.module, role, link, kwargs, pin), name)


def service(
    peer: ModuleType, link: Link, pin: int | None
) -> contextlib.AbstractContextManager[Any]:
    """The peer's per-measurement infrastructure (a broker), or nothing."""
    factory = getattr(peer, "service", None)
    return factory(link, pin) if factory else contextlib.nullcontext()


def measure_rtt(
    spec: PeerSpec, peer: ModuleType, args: argparse.Namespace, rounds: int, warmup: int
) -> list[float]:
    """Ping-pong between two processes pinned to ``args.cpu``; RTTs in seconds."""
    link = Link(HOST, free_ports(2, HOST), spec.options)
    timeout = SETUP_TIMEOUT + (warmup + rounds) * 2e-3  # fails above 2 ms/RTT
    children: list[Spawned] = []
    with service(peer, link, args.cpu):
        try:
            pong = _role(spec, "pong", link, {}, args.cpu)
            children.append(pong)
            pong.expect("ready", SETUP_TIMEOUT)
            kwargs = {"warmup": warmup, "rounds": rounds}
            ping = _role(spec, "ping", link, kwargs, args.cpu)
            children.append(ping)
            rtts: list[float] = ping.expect("result", timeout)
            pong.expect("result", EXIT_GRACE)
            return rtts
        finally:
            for child in children:
                child.stop(EXIT_GRACE)


def measure_throughput(spec: PeerSpec, peer: ModuleType, args: argparse.Namespace) -> SinkResult:
    """Source to sink, ``args.messages`` messages; what the sink counted."""
    link = Link(HOST, free_ports(2, HOST), spec.options)
    pin = args.cpu if args.pin_throughput else None
    timeout = SETUP_TIMEOUT + IDLE_TIMEOUT + args.messages * 50e-6  # fails below 20k msg/s
    children: list[Spawned] = []
    with service(peer, link, pin):
        try:
            sink = _role(spec, "sink", link,
                         {"count": args.messages, "idle_timeout": IDLE_TIMEOUT}, pin)  # fmt: skip
            children.append(sink)
            sink.expect("ready", SETUP_TIMEOUT)
            source = _role(spec, "source", link, {"count": args.messages}, pin)
            children.append(source)
            result: SinkResult = sink.expect("result", timeout)
            source.send("release")  # its sink has reported: it may close its connection
            source.expect("result", SETUP_TIMEOUT)
            return result
        finally:
            for child in children:
                child.stop(EXIT_GRACE)


def percentile(sorted_values: list[float], q: float) -> float:
    """The ``q`` quantile (0..1) of already sorted values, linear between neighbours."""
    return statistics.quantiles(sorted_values, n=1000, method="inclusive")[round(q * 1000) - 1]


def run_spec(spec: PeerSpec, args: argparse.Namespace) -> Row:
    """The measurements ``spec`` asks for; a failure ends up in ``Row.error``."""
    row = Row(spec.label)
    peer = importlib.import_module(spec.module)
    link = Link(HOST, (0, 0), spec.options)
    why_not = getattr(peer, "missing", lambda _link: None)(link)
    if why_not:
        row.error = f"skipped: {why_not}"
        return row
    row.note = getattr(peer, "describe", lambda _link: "")(link)
    try:
        if "rtt" in spec.measure:
            rtts = []
            for pair in range(args.pairs):  # each pair its own processes, its own layout
                share = args.roundtrips // args.pairs + (pair < args.roundtrips % args.pairs)
                times = sorted(t * 1e6 for t in measure_rtt(spec, peer, args, share, args.warmup))
                row.rtt_p50_pairs_us.append(percentile(times, 0.50))
                rtts += times
            rtts.sort()
            row.rtt_p50_us = percentile(rtts, 0.50)
            row.rtt_p99_us = percentile(rtts, 0.99)
            row.rtt_mean_us = statistics.fmean(rtts)
            row.roundtrips = len(rtts)
        if "throughput" in spec.measure:
            sink = measure_throughput(spec, peer, args)
            row.sent, row.received = args.messages, sink.received
            row.lost = args.messages - sink.received
            if sink.received > 1 and sink.seconds > 0:
                row.rate_msg_s = (sink.received - 1) / sink.seconds
    except Exception as exc:
        row.error = f"{type(exc).__name__}: {exc}"
    return row


def span(values: list[float] | None) -> str:
    """Lowest-highest of several figures (each process pair's p50), "-" if there are none."""
    if not values:
        return "-"
    return f"{min(values):.1f}-{max(values):.1f}" if len(values) > 1 else f"{values[0]:.1f}"


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def add_ratios(rows: list[Row]) -> None:
    """Set each row's ``rtt_p50_x_raw`` (RTT p50 over raw TCP's), if raw TCP was measured."""
    floor = next((r.rtt_p50_us for r in rows if r.peer == RAW_LABEL and r.rtt_p50_us), None)
    for r in rows:
        if floor and r.rtt_p50_us:
            r.rtt_p50_x_raw = r.rtt_p50_us / floor


LEGEND = """\
RTT in microseconds, both processes pinned to one CPU, p50/p99 over every pair of processes
(pairs: each pair's own p50, lowest-highest); x raw: RTT p50 over raw TCP's.
msg/s: at the sink, from its first to its last arrival (over what arrived, if lost)."""


def table(rows: list[Row]) -> str:
    """The rows as a fixed-width text table (see LEGEND)."""
    head = (f"{'peer':<30} {'RTT p50':>9} {'RTT p99':>9} {'pairs':>11} {'x raw':>6} "
            f"{'msg/s':>11} {'received':>17} {'loss':>14}  note")  # fmt: skip
    lines = [head, "-" * len(head)]
    for r in rows:
        if r.error:
            lines.append(f"{r.peer:<30} {r.error.splitlines()[0]}")
            continue
        got = f"{r.received}/{r.sent}" if r.sent else "-"
        if not r.sent:
            loss = "-"
        elif r.lost:
            loss = f"{r.lost} ({100 * r.lost / r.sent:.1f}%)"
        else:
            loss = "0"
        ratio = _fmt(r.rtt_p50_x_raw, ".2f")
        pairs = span(r.rtt_p50_pairs_us)
        lines.append(
            f"{r.peer:<30} {_fmt(r.rtt_p50_us, '.1f'):>9} {_fmt(r.rtt_p99_us, '.1f'):>9} "
            f"{pairs:>11} {ratio:>6} {_fmt(r.rate_msg_s, ',.0f'):>11} {got:>17} {loss:>14}  "
            f"{r.note}"
        )
    return "\n".join(lines)


def environment() -> dict[str, Any]:
    """Python, machine, and the versions of the packages the peers use."""
    versions: dict[str, str | None] = {}
    for dist in ("msgpack", "uvloop", "pyzmq", "paho-mqtt", "eclipse-zenoh"):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[dist] = None
    return {
        "python": sys.version.split()[0],
        "implementation": platform.python_implementation(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "packages": versions,
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--roundtrips", type=int, default=50_000, help="measured round trips")
    p.add_argument("--warmup", type=int, default=5_000, help="round trips before measuring")
    p.add_argument("--pairs", type=int, default=3,
                   help="ping/pong process pairs the round trips are shared among")  # fmt: skip
    p.add_argument("--messages", type=int, default=500_000, help="messages for throughput")
    p.add_argument("--peers", default=",".join(PEERS),
                   help=f"comma-separated, from {','.join(PEERS)}")  # fmt: skip
    p.add_argument("--cpu", type=int, default=0, help="CPU both round-trip processes run on")
    p.add_argument("--pin-throughput", action="store_true",
                   help="pin the throughput processes to --cpu too")  # fmt: skip
    p.add_argument("--json", metavar="PATH", help="also write the results as JSON here")
    args = p.parse_args(argv)
    unknown = [name for name in args.peers.split(",") if name not in PEERS]
    if unknown:
        p.error(f"unknown peer(s) {','.join(unknown)}; choose from {','.join(PEERS)}")
    if min(args.roundtrips, args.messages) < 2 or args.warmup < 0 or args.pairs < 1:
        p.error("--roundtrips and --messages need at least 2, --warmup at least 0, --pairs 1")
    if args.roundtrips < 2 * args.pairs:
        p.error("--roundtrips needs at least 2 round trips per pair")
    return args


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Every selected peer, one after the other; the document ``--json`` writes (settings,
    environment, and a row per peer, a peer that failed or was skipped with its ``error``)."""
    specs = [spec for name in args.peers.split(",") for spec in PEERS[name]]
    rows: list[Row] = []
    for spec in specs:
        t0 = time.monotonic()
        rows.append(run_spec(spec, args))
        status = rows[-1].error.splitlines()[0] if rows[-1].error else "ok"
        print(f"  {spec.label}: {status} ({time.monotonic() - t0:.1f} s)", flush=True)
    add_ratios(rows)
    return {"settings": {k: v for k, v in vars(args).items() if k != "json"},
            "environment": environment(), "rows": [asdict(r) for r in rows]}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    print(f"loopback {HOST}, 8-byte payloads, {args.roundtrips} round trips "
          f"(+{args.warmup} warm-up) pinned to CPU {args.cpu}, {args.messages} messages "
          f"one way ({'pinned' if args.pin_throughput else 'unpinned'})", flush=True)  # fmt: skip
    started = time.monotonic()
    doc = measure(args)
    rows = [Row(**r) for r in doc["rows"]]
    print(f"\n{table(rows)}\n{LEGEND}\ntotal {time.monotonic() - started:.0f} s")
    for r in rows:
        if r.error and "\n" in r.error:
            print(f"\n{r.peer}:\n{r.error}", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=2)
    return 0 if all(not r.error or r.error.startswith("skipped") for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
