"""Join storm on CAN: N nodes start at the same instant; how long until every one has a TxNode?

One CAN-ECB process (``ups can-broker``, fresh database each run) serves the bus. K worker
processes (``--workers``, default 4) each host N/K nodes, which reach the bus as ``--layout``
says:

- ``spec`` (default): every node is given the bus spec, ``Node(can=SPEC)``, as an application
  writes it; the nodes of one process share one connection (``CanLink.shared``);
- ``link``: the worker opens one ``CanLink`` and hands it to every node;
- ``bus``: every node gets a python-can bus of its own: a connection per node, as when every
  node is a process of its own (and as ``spec`` was before nodes shared connections).

Node ids (``--ids``) are random 64-bit numbers (seeded: ``--seed``, printed) or sequential
(0x5000, 0x5001, ...). ``--hog`` holds every CPU with a busy process during the runs (a
loaded machine). All workers wait for a common wall-clock instant T0, then start all their
nodes at once. A node's join time is when
its ``start()`` returned, minus T0; a node not joined within ``--timeout`` seconds counts as
failed. A plain python-can bus in this process counts every frame on the bus from T0 until
the last node joined (until the timeout if some never did), management frames apart.

Reported per N and repeat: time until all joined (the slowest join), median join time, nodes
joined, whether their TxNodes are all distinct, and frames on the bus (in total and per joined
node). ``--json PATH`` also writes every node's id, TxNode and join time.

The default bus is udp_multicast on a free port, so it must run inside a private network
namespace (it refuses to run otherwise); or give a SocketCAN bus inside scripts/uml-run:

    scripts/netns-run .venv/bin/python -m ups.benchmarks.join_storm --nodes 10,50,127 --repeat 3
    scripts/netns-run .venv/bin/python -m ups.benchmarks.join_storm --layout bus --ids sequential \
        --workers 1 --nodes 60 --hog
    scripts/uml-run .venv/bin/python -m ups.benchmarks.join_storm --can socketcan:vcan0
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import contextlib
import json
import os
import queue
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from ups import Node
from ups._canlink import CanLink, open_bus
from ups._canproto import is_management
from ups.benchmarks._procs import ROOT, Child, cpu_hog

ECB_READY = "CAN-ECB on"
GRACE = 10.0  # seconds past the timeout before a silent worker is given up and stopped


# --- the worker: N/K nodes on one link, started at T0 ---------------------------------------


def emit(record: dict[str, Any]) -> None:
    print(json.dumps(record), flush=True)


LAYOUTS = ("spec", "link", "bus")


async def worker(
    index: int, bus: str, t0: float, timeout: float, ids: list[int], layout: str
) -> None:
    """Host one node per id, on the bus as ``layout`` says; start them all at ``t0``; print
    one line per node."""
    loop = asyncio.get_running_loop()
    link = CanLink.open(bus) if layout == "link" else None
    buses = [open_bus(bus) for _ in ids] if layout == "bus" else []
    where: list[str | can.BusABC | CanLink] = (
        [link] * len(ids) if link is not None else list(buses) if buses else [bus] * len(ids)
    )
    nodes = [Node(can=w, node_id=i, join_timeout=timeout) for w, i in zip(where, ids, strict=True)]
    slack = t0 - time.time()
    emit({"worker": index, "ready": True, "slack": slack})  # slack < 0: this worker was late
    await asyncio.sleep(max(0.0, slack))

    async def join(node: Node) -> None:
        record: dict[str, Any] = {"worker": index, "node_id": f"{node.node_id:016x}"}
        try:
            async with asyncio.timeout(t0 + timeout - time.time()):
                await node.start()
            record["join_s"] = time.time() - t0
            record["txnode"] = node.stats()["txnode"]
        except Exception as exc:  # TimeoutError, BrokerUnavailable, Exhausted, ...
            record["error"] = f"{type(exc).__name__}: {exc}"
        emit(record)

    await asyncio.gather(*(join(node) for node in nodes))
    emit({"worker": index, "done": True})
    # Stay on the bus until the benchmark has its figures (stdin closes), bounded all the same.
    eof = loop.create_future()
    fd = sys.stdin.fileno()

    def on_stdin() -> None:
        if not os.read(fd, 4096) and not eof.done():
            eof.set_result(None)

    loop.add_reader(fd, on_stdin)
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(eof, max(1.0, t0 + timeout + GRACE - time.time()))
    loop.remove_reader(fd)
    for node in nodes:
        with contextlib.suppress(Exception):
            await node.close()
    if link is not None:
        link.close()
    for one in buses:
        one.shutdown()


# --- the benchmark process -------------------------------------------------------------------


class FrameCounter:
    """Every frame the bus carries from ``start`` on, read by a plain python-can bus."""

    def __init__(self, bus: str, start: float) -> None:
        self.bus = open_bus(bus)
        self.start = start
        self.times = array("d")  # receive time of each frame (the kernel's, where given)
        self.management = bytearray()  # 1 for each management frame
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            frame = self.bus.recv(0.05)
            if frame is None:
                continue
            stamp = frame.timestamp or time.time()
            if stamp >= self.start:
                self.times.append(stamp)
                self.management.append(frame.is_extended_id and is_management(frame.arbitration_id))

    def count(self, end: float) -> tuple[int, int]:
        """(management frames, other frames) received from ``start`` to ``end``."""
        n = bisect.bisect_right(self.times, end)  # frames arrive in time order
        mgmt = sum(self.management[:n])
        return mgmt, n - mgmt

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.bus.shutdown()


@dataclass
class Run:
    n: int
    repeat: int
    seed: int
    layout: str = "spec"
    ids: str = "random"
    workers: int = 4
    hog: bool = False
    t0: float = 0.0  # wall clock: the instant every node started
    nodes: list[dict[str, Any]] = field(default_factory=list)
    late_workers: dict[int, float] = field(default_factory=dict)
    frames_mgmt: int = 0
    frames_other: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def joined(self) -> list[dict[str, Any]]:
        return [r for r in self.nodes if "join_s" in r]

    def summary(self) -> dict[str, Any]:
        times = sorted(r["join_s"] for r in self.joined)
        txnodes = [r["txnode"] for r in self.joined]
        frames = self.frames_mgmt + self.frames_other
        return {
            "n": self.n,
            "repeat": self.repeat,
            "seed": self.seed,
            "layout": self.layout,
            "ids": self.ids,
            "workers": self.workers,
            "hog": self.hog,
            "t0": self.t0,
            "joined": len(times),
            "all_joined": len(times) == self.n,
            "time_all_s": times[-1] if len(times) == self.n else None,
            "slowest_s": times[-1] if times else None,
            "median_s": statistics.median(times) if times else None,
            "distinct_txnodes": len(set(txnodes)) == len(txnodes),
            "frames": frames,
            "frames_mgmt": self.frames_mgmt,
            "frames_other": self.frames_other,
            "frames_per_join": frames / len(times) if times else None,
            "late_workers": self.late_workers,
            "problems": self.problems,
        }


SEQUENTIAL_FIRST = 0x5000  #: the first of ``--ids sequential``


def node_ids(n: int, seed: int, kind: str = "random") -> list[int]:
    """``n`` distinct node ids: random 64-bit ones, the same for the same seed, or sequential
    from ``SEQUENTIAL_FIRST``."""
    if kind == "sequential":
        return [SEQUENTIAL_FIRST + i for i in range(n)]
    rng = random.Random(seed)
    ids: list[int] = []
    while len(ids) < n:
        candidate = rng.getrandbits(64)
        if candidate not in ids:
            ids.append(candidate)
    return ids


def storm(bus: str, n: int, repeat: int, seed: int, args: argparse.Namespace) -> Run:
    """One join storm of ``n`` nodes against a fresh CAN-ECB."""
    workers = min(args.workers, n)
    run = Run(n, repeat, seed, args.layout, args.ids, workers, args.hog)
    ids = node_ids(n, seed, args.ids)
    children: list[Child] = []
    counter: FrameCounter | None = None
    with tempfile.TemporaryDirectory(prefix="join-storm-") as tmp:
        try:
            ecb = Child(
                [sys.executable, "-m", "upscli", "can-broker", "--can", bus,
                 "--db", str(Path(tmp) / "ecb.db")],
                "can-broker",
            )  # fmt: skip
            children.append(ecb)
            ecb.wait_stderr(ECB_READY, 20)
            t0 = run.t0 = time.time() + args.lead
            counter = FrameCounter(bus, t0)
            for k in range(workers):
                share = ids[k::workers]
                cmd = [sys.executable, "-m", "ups.benchmarks.join_storm", "--worker", str(k),
                       "--can", bus, "--t0", repr(t0), "--timeout", str(args.timeout),
                       "--layout", args.layout,
                       "--worker-ids", ",".join(f"{i:x}" for i in share)]  # fmt: skip
                children.append(Child(cmd, f"worker {k}"))
            collect(run, children[1:], t0 + args.timeout + GRACE)
            joined = run.joined
            end = t0 + (max(r["join_s"] for r in joined) if len(joined) == n else args.timeout)
            time.sleep(max(0.0, min(end + 0.2 - time.time(), 1.0)))  # let the last frames in
            run.frames_mgmt, run.frames_other = counter.count(end)
        finally:
            if counter is not None:
                counter.close()
            for child in children[1:]:
                child.close_stdin()
            for child in children[1:]:
                code = child.finish(10.0)
                if code != 0:
                    run.problems.append(f"{child.label} exited {code}: {child.tail(5)}")
            if children:
                children[0].finish(0.1)  # the CAN-ECB serves until told to stop
    return run


def collect(run: Run, workers: list[Child], deadline: float) -> None:
    """Gather every worker's node lines until all reported or ``deadline`` (wall clock)."""
    pending = {id(w): w for w in workers}
    while pending and time.time() < deadline:
        for key, child in list(pending.items()):
            try:
                record = child.records.get(timeout=0.02)
            except queue.Empty:
                continue
            if record is None or record.get("done"):  # None: the worker ended early
                del pending[key]
            elif record.get("ready"):
                if record["slack"] < 0:
                    run.late_workers[record["worker"]] = -record["slack"]
            else:
                run.nodes.append(record)
    for child in pending.values():
        run.problems.append(f"{child.label} gave no result by the deadline")
    missing = run.n - len(run.nodes)
    if missing:
        run.problems.append(f"{missing} node(s) never reported")


def private_multicast_bus() -> str:
    """A udp_multicast bus on a free port (as tests/procs.py builds it)."""
    port_holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with port_holder:
        port_holder.bind(("127.0.0.1", 0))
        port = port_holder.getsockname()[1]
    return f"udp_multicast:239.74.163.2,port={port}"


def refuse_open_multicast(bus: str) -> None:
    """Multicast must never leave the machine: only inside a namespace with no default route."""
    if not bus.startswith("udp_multicast"):
        return
    routes = subprocess.run(
        ["ip", "route", "show", "default"], capture_output=True, text=True, check=False
    )
    if routes.returncode != 0 or routes.stdout.strip() or os.environ.get("UPS_IN_NETNS") != "1":
        sys.exit(
            "join_storm: udp_multicast needs a private network namespace with no default route;"
            " run it through scripts/netns-run"
        )


def fmt(value: float | None, spec: str = ".2f") -> str:
    return "-" if value is None else format(value, spec)


def print_table(rows: list[dict[str, Any]]) -> None:
    print(
        f"{'layout':>6} {'ids':>10} {'K':>2} {'hog':>3} {'N':>4} {'rep':>3} {'joined':>8}"
        f" {'all joined':>10} {'median':>7} {'slowest':>7}"
        f" {'distinct':>8} {'frames':>7} {'mgmt':>7} {'per join':>8}  late workers / problems"
    )
    for r in rows:
        notes = [f"worker {k} late {s:.2f} s" for k, s in r["late_workers"].items()]
        notes += [p.splitlines()[0] for p in r["problems"]]
        print(
            f"{r['layout']:>6} {r['ids']:>10} {r['workers']:>2} {'yes' if r['hog'] else 'no':>3}"
            f" {r['n']:>4} {r['repeat']:>3} {r['joined']:>4}/{r['n']:<3}"
            f" {fmt(r['time_all_s']):>10} {fmt(r['median_s']):>7} {fmt(r['slowest_s']):>7}"
            f" {'yes' if r['distinct_txnodes'] else 'NO':>8} {r['frames']:>7}"
            f" {r['frames_mgmt']:>7} {fmt(r['frames_per_join'], '.1f'):>8}  {'; '.join(notes)}"
        )
    print("(seconds from T0; 'all joined' is the slowest join when every node joined, else -)")


def git_commit() -> str | None:
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        )
        return out.stdout.strip()
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", default="10,50,127", help="joiner counts (default 10,50,127)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per count (default 3)")
    parser.add_argument("--workers", type=int, default=4, help="joiner processes (default 4)")
    parser.add_argument(
        "--layout",
        choices=LAYOUTS,
        default="spec",
        help="how nodes reach the bus (default spec: see above)",
    )
    parser.add_argument(
        "--ids",
        choices=("random", "sequential"),
        default="random",
        help="node ids (default random)",
    )
    parser.add_argument("--hog", action="store_true", help="hold every CPU busy meanwhile")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds per run (60)")
    parser.add_argument("--lead", type=float, default=3.0, help="seconds from launch to T0 (3)")
    parser.add_argument("--seed", type=int, default=1, help="node ids of run i use seed+i")
    parser.add_argument("--can", help="bus spec (default: udp_multicast on a free port)")
    parser.add_argument("--json", type=Path, help="also write every figure and node here")
    parser.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--t0", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--worker-ids", help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.worker is not None:
        ids = [int(i, 16) for i in args.worker_ids.split(",")]
        asyncio.run(worker(args.worker, args.can, args.t0, args.timeout, ids, args.layout))
        return

    bus = args.can or private_multicast_bus()
    refuse_open_multicast(bus)
    print(
        f"join storm on {bus}: {args.workers} worker processes, layout {args.layout}, "
        f"{args.ids} ids, timeout {args.timeout:g} s{', CPU hog' if args.hog else ''}"
    )
    runs: list[Run] = []
    with contextlib.ExitStack() as stack:
        if args.hog:  # bounded: every run's time at most, with room to spare
            budget = len(args.nodes.split(",")) * args.repeat * (args.timeout + GRACE + 30)
            stack.enter_context(cpu_hog(budget))
        storms(bus, [int(n) for n in args.nodes.split(",")], args, runs)
    rows = [r.summary() for r in runs]
    print()
    print_table(rows)
    if args.json:
        report = {
            "bus": bus,
            "commit": git_commit(),
            "workers": args.workers,
            "layout": args.layout,
            "ids": args.ids,
            "hog": args.hog,
            "timeout_s": args.timeout,
            "runs": [{**r.summary(), "nodes": r.nodes} for r in runs],
        }
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        print(f"written to {args.json}")


def storms(bus: str, counts: list[int], args: argparse.Namespace, runs: list[Run]) -> None:
    i = 0
    for n in counts:
        for rep in range(1, args.repeat + 1):
            seed = args.seed + i
            i += 1
            print(f"N={n} repeat {rep}: node ids from seed {seed} ...", flush=True)
            run = storm(bus, n, rep, seed, args)
            runs.append(run)
            s = run.summary()
            print(
                f"  {s['joined']}/{n} joined, slowest {fmt(s['slowest_s'])} s, "
                f"{s['frames']} frames",
                flush=True,
            )


if __name__ == "__main__":
    can.util.set_logging_level("warning")
    main()
