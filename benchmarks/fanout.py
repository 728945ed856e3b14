"""Lossless fan-out on loopback: one publisher, N subscriber processes, UPS against pyzmq.

For each N, in one run: the publisher sends M 8-byte messages to N subscribers, each a process
that counts what arrives. Lossless: UPS publishes with ``wait=True`` (backpressure), pyzmq runs
with HWM=0 (no limit). Reported: messages delivered per second in all (N x M over the time from
the first arrival anywhere to the last), and per subscriber; and UPS / pyzmq. UPS runs twice
when its compiled build (``UPS_COMPILE=1``, :mod:`benchmarks._compiled`) can be made here: as
it is installed, and compiled (publisher and subscribers). Every child is spawned here, every
wait bounded, every child stopped by its PID.

    .venv/bin/python -m ups.benchmarks.fanout [--subscribers 1,2,4,8,16,32] [--messages M]
        [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import importlib.util
import json
import sys
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from ups.benchmarks import _compiled
from ups.benchmarks._procs import Spawned, free_port, process

HOST = "127.0.0.1"
TIMEOUT = 120.0
PROBE = b"probe"


def _loop_run(main: Any) -> Any:
    try:
        import uvloop
    except ImportError:
        return asyncio.run(main)
    return uvloop.run(main)


# --- UPS -------------------------------------------------------------------------------------


def _ups_sink(address: str, index: int, count: int, compiled: str | None, pipe: Connection) -> None:
    Node = _compiled.import_ups(compiled).Node

    async def main() -> None:
        seen = [0, 0.0, 0.0]  # count, first, last
        loop = asyncio.get_running_loop()
        done = loop.create_future()

        def on_event(msg: Any) -> None:
            seen[2] = time.perf_counter()
            if not seen[0]:
                seen[1] = seen[2]
            seen[0] += 1
            if seen[0] == count and not done.done():
                done.set_result(None)

        async with Node(broker=address, name=f"fan-{index}", node_id=0xFA0000 + index) as node:
            await node.subscribe("bench/fanout", callback=on_event)
            pipe.send(("ready", None))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done, TIMEOUT)
        pipe.send(("result", tuple(seen)))

    _loop_run(main())


def _ups_source(
    address: str, subscribers: int, count: int, compiled: str | None, pipe: Connection
) -> None:
    Node = _compiled.import_ups(compiled).Node

    async def main() -> None:
        async with Node(broker=address, name="fan-source", node_id=0xFAFFFF) as node:
            await node.advertise("bench/fanout")
            deadline = time.monotonic() + TIMEOUT
            while node.stats()["peers"] < subscribers:
                if time.monotonic() > deadline:
                    raise TimeoutError("not every subscriber was reached")
                await asyncio.sleep(0.01)
            data = bytes(8)
            for _ in range(count):
                await node.publish("bench/fanout", data, wait=True)
            await asyncio.to_thread(pipe.recv)  # until the sinks are done

    _loop_run(main())


def ups(subscribers: int, count: int, compiled: str | None = None) -> dict[str, Any]:
    """UPS as installed, or (``compiled``: the directory of the compiled copy) compiled."""
    address = f"{HOST}:{free_port()}"
    cmd = [sys.executable, "-m", "upscli", "broker", "--listen", address, "--recovery", "0"]
    with process(cmd, "TCP-ECB on"):
        return _measure(_ups_sink, _ups_source, address, subscribers, count, (compiled,))


# --- pyzmq -----------------------------------------------------------------------------------


def _zmq_sink(address: str, index: int, count: int, pipe: Connection) -> None:
    import zmq

    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.RCVHWM, 0)
    sock.setsockopt(zmq.SUBSCRIBE, b"")
    sock.connect(address)
    sock.setsockopt(zmq.RCVTIMEO, int(TIMEOUT * 1000))
    try:
        while sock.recv() != PROBE:  # the publisher probes until every subscriber is in
            pass
        pipe.send(("ready", None))
        seen = [0, 0.0, 0.0]
        while seen[0] < count:
            if sock.recv() == PROBE:
                continue
            seen[2] = time.perf_counter()
            if not seen[0]:
                seen[1] = seen[2]
            seen[0] += 1
    except zmq.Again:
        pass
    finally:
        sock.close(linger=0)
        ctx.term()
    pipe.send(("result", tuple(seen)))


def _zmq_source(address: str, subscribers: int, count: int, pipe: Connection) -> None:
    import zmq

    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUB)
    sock.setsockopt(zmq.SNDHWM, 0)
    sock.bind(address)
    try:
        deadline = time.monotonic() + TIMEOUT
        while not pipe.poll(0.01):  # "all ready", from the parent
            sock.send(PROBE)
            if time.monotonic() > deadline:
                raise TimeoutError("not every subscriber joined")
        pipe.recv()
        data = bytes(8)
        for _ in range(count):
            sock.send(data)
        pipe.recv()
    finally:
        sock.close(linger=0)
        ctx.term()


def zmq(subscribers: int, count: int) -> dict[str, Any]:
    return _measure(_zmq_sink, _zmq_source, f"tcp://{HOST}:{free_port()}", subscribers, count, ())


# --- both ------------------------------------------------------------------------------------


def _measure(
    sink: Any, source: Any, address: str, subscribers: int, count: int, extra: tuple[Any, ...]
) -> dict[str, Any]:
    """One source and ``subscribers`` sinks, each a spawned process: ``extra`` goes to each
    after its usual arguments. The sinks report (count, first, last) when done."""
    sinks: list[Spawned] = []
    src: Spawned | None = None
    try:
        if source is _zmq_source:  # zmq: the publisher binds first
            src = Spawned(source, (address, subscribers, count, *extra), "fan-out source")
        for i in range(subscribers):
            sinks.append(Spawned(sink, (address, i, count, *extra), f"fan-out sink {i}"))
        for child in sinks:
            child.expect("ready", TIMEOUT)
        if src is not None:
            src.send("go")
        else:
            src = Spawned(source, (address, subscribers, count, *extra), "fan-out source")
        results = [child.expect("result", TIMEOUT + 30) for child in sinks]
        src.send("done")
    finally:
        for child in [*([src] if src is not None else []), *sinks]:
            child.stop(10.0)
    received = sum(r[0] for r in results)
    span = max(r[2] for r in results) - min(r[1] for r in results)
    return {
        "subscribers": subscribers,
        "sent": count,
        "received": received,
        "lost": subscribers * count - received,
        "total_msgs_per_s": received / span if span > 0 else 0.0,
        "per_subscriber_msgs_per_s": received / span / subscribers if span > 0 else 0.0,
    }


def run(subscribers: tuple[int, ...], count: int) -> list[dict[str, Any]]:
    """A row per N: UPS (its failure ends the run), the compiled UPS (``ups_compiled``, None when
    it cannot be built here), and pyzmq beside them (``None`` when pyzmq is not installed;
    ``{"error": ...}`` when it failed, which does not end the run)."""
    have_zmq = importlib.util.find_spec("zmq") is not None
    compiled = None if _compiled.unavailable() else str(_compiled.build())
    rows = []
    for n in subscribers:
        row: dict[str, Any] = {"subscribers": n, "ups": ups(n, count), "zmq": None}
        row["ups_compiled"] = ups(n, count, compiled) if compiled else None
        if have_zmq:
            try:
                row["zmq"] = zmq(n, count)
            except (TimeoutError, OSError, RuntimeError) as exc:
                row["zmq"] = {"error": f"{type(exc).__name__}: {exc}"}
        if row["zmq"] and row["zmq"].get("total_msgs_per_s"):
            row["ratio"] = row["ups"]["total_msgs_per_s"] / row["zmq"]["total_msgs_per_s"]
            if row["ups_compiled"]:
                row["ratio_compiled"] = (
                    row["ups_compiled"]["total_msgs_per_s"] / row["zmq"]["total_msgs_per_s"]
                )
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--subscribers", default="1,2,4,8,16,32")
    parser.add_argument("--messages", type=int, default=100_000, help="per subscriber")
    parser.add_argument("--json", metavar="PATH", help="also write the rows as JSON here")
    args = parser.parse_args()
    rows = run(tuple(int(n) for n in args.subscribers.split(",")), args.messages)
    print(f"{'subs':>5}{'UPS msg/s':>12}{'lost':>6}{'compiled':>12}{'lost':>6}"
          f"{'pyzmq msg/s':>13}{'lost':>6}{'x zmq':>7}{'compiled':>9}")  # fmt: skip
    for r in rows:
        z = {"total_msgs_per_s": 0.0, "lost": "-", **(r["zmq"] or {})}
        c = {"total_msgs_per_s": 0.0, "lost": "-", **(r["ups_compiled"] or {})}
        print(
            f"{r['subscribers']:>5}{r['ups']['total_msgs_per_s']:>12,.0f}{r['ups']['lost']:>6}"
            f"{c['total_msgs_per_s']:>12,.0f}{c['lost']:>6}"
            f"{z['total_msgs_per_s']:>13,.0f}{z['lost']:>6}{r.get('ratio', 0.0):>7.2f}"
            f"{r.get('ratio_compiled', 0.0):>9.2f}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
