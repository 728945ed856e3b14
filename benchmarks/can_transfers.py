"""Events larger than one frame on CAN: UPS against python-can's raw floor, classic and CAN FD.

For 8 B, 64 B, 1 KiB and 4 KiB events, on a classic and on a CAN FD python-can ``virtual``
bus in one process (a CAN-ECB hosted beside two nodes):

- latency: one event at a time, publish to ``get_msg`` (p50/p99), against sending the same
  frames with two raw python-can buses and receiving them all;
- throughput: a burst of events, received whole, against the same frames raw;
- bus efficiency: event bits / bus bits of the transfer's frames, without and with worst-case
  bit stuffing (FD frames counted at one bit rate: bit-rate switching only shortens them), and
  the events per second that a real 1 Mbit/s bus would carry at that efficiency.

A virtual bus has no bit rate, so latency and throughput here are the software's cost, the
floor under what a real bus adds. Run: ``.venv/bin/python -m ups.benchmarks.can_transfers
[--quick] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import can

from ups import Node
from ups import _cantransfer as t
from ups.broker import hosted_can_ecb
from ups.rt import frame_bits

SIZES = (8, 64, 1024, 4096)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def _frames(size: int, fd: bool) -> list[bytes]:
    if size <= 8:
        return [bytes(size)]
    return t.segment(bytes(size), 0, 64 if fd else 8)


async def _ups(bus: str, size: int, samples: int, burst: int) -> dict[str, float]:
    data = bytes(range(256)) * (size // 256) + bytes(size % 256)
    with tempfile.TemporaryDirectory() as tmp:
        async with (
            hosted_can_ecb(bus, db=Path(tmp) / "ecb.db"),
            Node(can=bus, node_id=1) as pub,
            Node(can=bus, node_id=2) as sub_node,
        ):
            sub = await sub_node.subscribe("bench", maxlen=burst + 1)
            await pub.advertise("bench", max_size=size)
            await pub.publish("bench", data)  # warm up: the subscriber follows the binding
            await sub.get_msg(timeout=5)
            latencies = []
            for _ in range(samples):
                start = time.perf_counter()
                await pub.publish("bench", data)
                await sub.get_msg(timeout=5)
                latencies.append((time.perf_counter() - start) * 1e6)
            start = time.perf_counter()
            for _ in range(burst):
                await pub.publish("bench", data)
            got = 0
            while got < burst:
                try:
                    msg = await sub.get_msg(timeout=2)
                except TimeoutError:
                    break
                got += msg.data == data
            elapsed = time.perf_counter() - start
            lost = sub_node.stats()["large_lost"] + burst - got
    return {
        "p50_us": statistics.median(latencies),
        "p99_us": _percentile(latencies, 0.99),
        "events_per_s": got / elapsed,
        "lost": lost,
    }


def _raw(size: int, fd: bool, samples: int, burst: int) -> dict[str, float]:
    frames = _frames(size, fd)
    channel = f"raw-{size}-{fd}-{time.monotonic_ns()}"
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    messages = [
        can.Message(arbitration_id=0x10003000, data=d, is_extended_id=True, is_fd=fd)
        for d in frames
    ]
    try:
        latencies = []
        for _ in range(samples):
            start = time.perf_counter()
            for msg in messages:
                tx.send(msg)
            for _ in messages:
                rx.recv(1)
            latencies.append((time.perf_counter() - start) * 1e6)
        start = time.perf_counter()
        for _ in range(burst):
            for msg in messages:
                tx.send(msg)
        for _ in range(burst * len(messages)):
            rx.recv(1)
        elapsed = time.perf_counter() - start
    finally:
        tx.shutdown()
        rx.shutdown()
    return {"p50_us": statistics.median(latencies), "events_per_s": burst / elapsed}


def _efficiency(size: int, fd: bool) -> dict[str, float]:
    frames = _frames(size, fd)
    payload = 8 * size
    bits = {s: sum(frame_bits(len(f), 29, s, fd) for f in frames) for s in ("none", "worst")}
    return {
        "frames": len(frames),
        "efficiency_none": payload / bits["none"],
        "efficiency_worst": payload / bits["worst"],
        "events_per_s_at_1mbit": 1_000_000 / bits["none"],
    }


async def main(quick: bool) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for fd in (False, True):
        for size in SIZES:
            samples = (60 if quick else 300) if size <= 1024 else (20 if quick else 100)
            burst = (200 if quick else 1000) if size <= 1024 else (50 if quick else 200)
            bus = f"virtual:bench-{size}-{int(fd)}-{time.monotonic_ns()}" + (",fd=True" * fd)
            ups = await _ups(bus, size, samples, burst)
            raw = _raw(size, fd, samples, burst)
            rows.append(
                {"bus": "fd" if fd else "classic", "size": size, "ups": ups, "raw": raw,
                 **_efficiency(size, fd)}
            )  # fmt: skip
    head = (
        f"{'bus':8}{'size':>6}{'frames':>7}{'p50 us':>9}{'p99 us':>9}{'raw p50':>9}{'ratio':>7}"
        f"{'ev/s':>9}{'raw ev/s':>10}{'ratio':>7}{'lost':>6}{'eff %':>7}{'worst %':>8}"
        f"{'ev/s@1M':>9}"
    )
    print("python-can virtual bus, one process (no bit rate: the software's cost)")
    print(head)
    for r in rows:
        u, w = r["ups"], r["raw"]
        print(
            f"{r['bus']:8}{r['size']:>6}{r['frames']:>7}{u['p50_us']:>9.0f}{u['p99_us']:>9.0f}"
            f"{w['p50_us']:>9.0f}{u['p50_us'] / w['p50_us']:>7.2f}{u['events_per_s']:>9.0f}"
            f"{w['events_per_s']:>10.0f}{u['events_per_s'] / w['events_per_s']:>7.2f}"
            f"{u['lost']:>6}{100 * r['efficiency_none']:>7.1f}{100 * r['efficiency_worst']:>8.1f}"
            f"{r['events_per_s_at_1mbit']:>9.0f}"
        )
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples")
    parser.add_argument("--json", metavar="PATH", help="write every figure as JSON")
    args = parser.parse_args()
    figures = asyncio.run(main(args.quick))
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
