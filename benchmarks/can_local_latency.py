"""Local notification and publish latency on CAN, as in Tables 3 and 4 of the paper.

Table 3: from the moment a frame reaches the node (the kernel's receive timestamp) until every
one of N local subscribers (N = 1..4, each an asyncio task awaiting ``get_msg``) holds the event.
Beside it, in the same run, the floor: a plain python-can bus in a blocking ``recv`` loop (the
same interface and kernel timestamp, no middleware).

Table 4: from a ``publish`` call until the frame is on the bus (the kernel's receive time of
its datagram at a python-can listener in the same process).

The frames come from a separate ``ups pub`` process, 1-byte payloads (as in the paper), paced so
that the receiver is idle when each one arrives. Runs on udp_multicast, so it must run inside a
private network namespace; or on SocketCAN vcan0 (inside scripts/uml-run):

    scripts/netns-run .venv/bin/python -m ups.benchmarks.can_local_latency
    scripts/uml-run .venv/bin/python -m ups.benchmarks.can_local_latency --can socketcan:vcan0
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import can

from ups import Node
from ups._canlink import CanLink, open_bus
from ups.benchmarks._procs import Child
from ups.broker.can_ecb import RECOVERY, CanEcb

PAPER_RTLINUX_AVG_US = {1: 17.5, 2: 22.6, 3: 27.9, 4: 34.3}  # Table 3
Summary = tuple[float, float, float, float, float]  # min, avg, p50, p99, max (µs)
_KEYS = ("min", "avg", "p50", "p99", "max")


def publisher(bus: str, count: int, rate: float) -> Child:
    """``ups pub`` of ``count`` events at ``rate``/s; it ends by itself."""
    return Child(
        [sys.executable, "-m", "upscli", "pub", "bench/latency", "01", "--can", bus,
         "--count", str(count), "--rate", str(rate), "--node-id", "0xBE7C4"],
        "ups pub",
    )  # fmt: skip


async def ups_latency(bus: str, subscribers: int, count: int, rate: float) -> list[float]:
    """Per event: time from kernel arrival until the last of ``subscribers`` tasks has it."""
    async with Node(can=bus, node_id=0x1A7E + subscribers) as node:
        subs = [await node.subscribe("bench/latency") for _ in range(subscribers)]
        done: list[float] = []

        async def consume(sub_index: int) -> None:
            for _ in range(count):
                msg = await subs[sub_index].get_msg(timeout=30)
                if sub_index == subscribers - 1:  # tasks run in order: the last one is last
                    done.append(time.time() - msg.timestamp)

        tasks = [asyncio.create_task(consume(i)) for i in range(subscribers)]
        proc = publisher(bus, count, rate)
        try:
            await asyncio.gather(*tasks)
            await asyncio.to_thread(proc.finish, 30.0)
        finally:
            proc.stop()  # at once when a measurement failed; else a no-op
        assert node.stats()["dropped"] == 0
        return done


def raw_latency(bus: str, count: int, rate: float) -> list[float]:
    """The floor: python-can's own blocking recv on the same interface."""
    listener = open_bus(bus)
    proc = publisher(bus, count, rate)
    lat: list[float] = []
    try:
        while len(lat) < count:
            frame = listener.recv(30)
            if frame is None:
                break
            now = time.time()
            if frame.is_extended_id and (frame.arbitration_id & 0x3FFF) >= 0x10:
                lat.append(now - frame.timestamp)
        proc.finish(30.0)
    finally:
        proc.stop()  # at once when a measurement failed; else a no-op
        listener.shutdown()
    return lat


async def publish_latency(bus: str, count: int, rate: float) -> list[float]:
    """Table 4: from the ``publish`` call until the frame is on the bus, i.e. the kernel's
    receive time of its datagram at a plain python-can listener on the same interface."""
    listener = open_bus(bus)
    try:
        async with Node(can=bus, node_id=0x1A7D) as node:
            await node.advertise("bench/publish")
            lat: list[float] = []
            for i in range(count):
                called = time.time()
                await node.publish("bench/publish", bytes([i & 0xFF]))
                while True:  # the listener hears every frame on the bus: find ours
                    frame = await asyncio.to_thread(listener.recv, 5)
                    if frame is None:
                        raise TimeoutError("the published frame never reached the listener")
                    if frame.data == bytes([i & 0xFF]) and frame.arbitration_id & 0x3FFF >= 0x10:
                        break
                lat.append(frame.timestamp - called)
                await asyncio.sleep(1 / rate)
            return lat
    finally:
        listener.shutdown()


def summary(values: list[float]) -> Summary:
    us = sorted(v * 1e6 for v in values)
    p99 = us[min(len(us) - 1, int(len(us) * 0.99))]
    return us[0], statistics.fmean(us), statistics.median(us), p99, us[-1]


async def measure(bus: str, count: int, rate: float, recovery: float = RECOVERY) -> dict[str, Any]:
    """Tables 3 and 4 on ``bus``, with a CAN-ECB of its own (its recovery window ``recovery``
    s: shorter only on a bus no node is on before it): the floor, UPS with 1..4 local
    subscribers, and the publish latency, each as {min, avg, p50, p99, max} in µs."""
    with tempfile.TemporaryDirectory() as tmp:
        link = CanLink.open(bus)
        ecb = CanEcb(link, Path(tmp) / "ecb.db", recovery=recovery)
        await ecb.start()
        try:
            raw = summary(await asyncio.to_thread(raw_latency, bus, count, rate))
            notify: dict[str, Summary] = {}
            for n in range(1, 5):
                notify[str(n)] = summary(await ups_latency(bus, n, count, rate))
            published = summary(await publish_latency(bus, count, rate))
        finally:
            ecb.close()
            link.close()
    return {
        "bus": bus,
        "count": count,
        "floor_us": dict(zip(_KEYS, raw, strict=True)),
        "local_notify_us": {n: dict(zip(_KEYS, r, strict=True)) for n, r in notify.items()},
        "publish_latency_us": dict(zip(_KEYS, published, strict=True)),
    }


def report(doc: dict[str, Any]) -> str:
    """``measure``'s figures as the table this module prints."""
    rows: list[tuple[str, dict[str, float], str]] = [
        ("python-can recv (floor)", doc["floor_us"], "")
    ]
    for n, figures in doc["local_notify_us"].items():
        rows.append((f"UPS, {n} local subscriber(s)", figures, n))
    lines = [
        f"local notification latency on {doc['bus']}, {doc['count']} events of 1 byte each",
        f"{'':28} {'min':>7} {'avg':>7} {'p50':>7} {'p99':>7} {'max':>7}  paper avg (RTLinux)",
    ]
    for label, f, n in rows:
        paper = f"{PAPER_RTLINUX_AVG_US[int(n)]:>6.1f} µs" if n else ""
        cells = " ".join(f"{f[k]:7.1f}" for k in _KEYS)
        lines.append(f"{label:28} {cells}  {paper}")
    ratio = doc["local_notify_us"]["1"]["p50"] / doc["floor_us"]["p50"]
    lines.append(f"(µs; p50 of UPS with 1 subscriber = {ratio:.2f}x the floor)")
    p = doc["publish_latency_us"]
    lines.append(
        f"publish call -> frame on the bus (Table 4): min {p['min']:.1f} avg {p['avg']:.1f} "
        f"p50 {p['p50']:.1f} p99 {p['p99']:.1f} max {p['max']:.1f} µs; paper (RTLinux) avg 153 µs"
    )
    return "\n".join(lines)


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--can", default="udp_multicast:239.74.163.2,port=43190")
    parser.add_argument("--count", type=int, default=500, help="events per configuration")
    parser.add_argument("--rate", type=float, default=500.0, help="events per second")
    parser.add_argument("--json", type=Path, help="also write every summary as JSON here")
    parser.add_argument(
        "--recovery", type=float, default=RECOVERY,
        help=f"the CAN-ECB's recovery window, s ({RECOVERY:g}; shorter only on a bus of its own)",
    )  # fmt: skip
    args = parser.parse_args()
    doc = await measure(args.can, args.count, args.rate, args.recovery)
    print(report(doc))
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    can.util.set_logging_level("warning")
    if "--uvloop" in sys.argv:
        import uvloop

        sys.argv.remove("--uvloop")
        uvloop.run(main())
    else:
        asyncio.run(main())
