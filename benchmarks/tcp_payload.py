"""One-way throughput by payload size on loopback TCP: UPS against raw TCP, side by side.

For each size (8 B to 1 MiB), in one run: a source process sends N events as fast as the
transport takes them and a sink process receives them; the rate is taken at the sink, from
its first to its last event, and every event's length is checked (and, for UPS, the
sequence numbers: ``lost``).

- raw TCP: blocking sockets, a 4-byte length before each message; the sink reads each message
  into a buffer with ``recv_into`` and makes it a ``bytes`` (what an application gets);
- UPS: a TCP-ECB child process, a source ``Node`` publishing with ``wait=True`` (backpressure:
  nothing dropped), a sink ``Node`` counting in a callback subscription; on uvloop when it is
  installed, or (``--loop asyncio``) the stdlib loop.

Every child is started here, every wait has a timeout, every child is stopped by its PID.

    .venv/bin/python -m ups.benchmarks.tcp_payload [--sizes 8,64,1024,65536,1048576] [--mib M]
        [--loop uvloop|asyncio] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import struct
import sys
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from ups.benchmarks._procs import Spawned, free_port, process

HOST = "127.0.0.1"
SIZES = (8, 64, 1024, 65536, 1 << 20)
TIMEOUT = 60.0  # for any one measurement
_LEN = struct.Struct(">I")


def _count(size: int, mib: float) -> int:
    """Events per measurement: about ``mib`` MiB, between 200 and 200,000 events."""
    return max(200, min(200_000, int(mib * (1 << 20) / size)))


# --- raw TCP ---------------------------------------------------------------------------------


def _raw_source(port: int, size: int, count: int, pipe: Connection) -> None:
    data = os.urandom(size)
    with socket.create_connection((HOST, port), timeout=TIMEOUT) as sock:
        head = _LEN.pack(size)
        for _ in range(count):
            sock.sendall(head + data if size <= 65536 else head)
            if size > 65536:
                sock.sendall(data)
    pipe.send(("sent", count))


def _raw_sink(srv: socket.socket, size: int, count: int) -> dict[str, Any]:
    srv.settimeout(TIMEOUT)
    conn, _ = srv.accept()
    conn.settimeout(TIMEOUT)
    buf = bytearray(max(size, 4))
    view = memoryview(buf)
    first = last = 0.0
    got = 0
    with conn:
        for i in range(count):
            _fill(conn, view[:4])
            length = _LEN.unpack_from(buf)[0]
            _fill(conn, view[:length])
            got += len(bytes(view[:length])) == size
            last = time.perf_counter()
            if i == 0:
                first = last
    return {"received": got, "seconds": last - first}


def _fill(conn: socket.socket, view: memoryview) -> None:
    done = 0
    while done < len(view):
        n = conn.recv_into(view[done:])
        if not n:
            raise ConnectionError("the source closed early")
        done += n


def raw_tcp(size: int, count: int) -> dict[str, Any]:
    with socket.socket() as srv:
        srv.bind((HOST, 0))
        srv.listen(1)
        source = Spawned(_raw_source, (srv.getsockname()[1], size, count), "raw source")
        try:
            result = _raw_sink(srv, size, count)
            source.expect("sent", TIMEOUT)
        finally:
            source.stop(TIMEOUT)
    return _rates(result, size, count)


# --- UPS -------------------------------------------------------------------------------------


def _run(main: Any) -> Any:
    if os.environ.get("UPS_BENCH_LOOP") == "asyncio":
        return asyncio.run(main)
    try:
        import uvloop
    except ImportError:
        return asyncio.run(main)
    return uvloop.run(main)


def _ups_source(port: int, size: int, count: int, pipe: Connection) -> None:
    from ups import Node

    async def main() -> None:
        data = os.urandom(size)
        async with Node(broker=f"{HOST}:{port}", name="payload-source", node_id=0xBA1) as node:
            await node.advertise("bench/payload")
            deadline = time.monotonic() + TIMEOUT
            while node.stats()["peers"] < 1:  # the sink's link, from the TCP-ECB's list
                if time.monotonic() > deadline:
                    raise TimeoutError("no link to the sink")
                await asyncio.sleep(0.01)
            for _ in range(count):
                await node.publish("bench/payload", data, wait=True)

    _run(main())
    pipe.send(("sent", count))


def _ups_sink(port: int, size: int, count: int, pipe: Connection) -> None:
    from ups import Message, Node

    async def main() -> dict[str, Any]:
        async with Node(broker=f"{HOST}:{port}", name="payload-sink", node_id=0xBA2) as node:
            loop = asyncio.get_running_loop()
            done = loop.create_future()
            seen = {"received": 0, "first": 0.0, "last": 0.0}

            def on_event(msg: Message) -> None:
                seen["last"] = time.perf_counter()
                if not seen["received"]:
                    seen["first"] = seen["last"]
                seen["received"] += len(msg.data) == size
                if seen["received"] == count and not done.done():
                    done.set_result(None)

            await node.subscribe("bench/payload", callback=on_event)
            pipe.send(("ready", None))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done, TIMEOUT)
            return {
                "received": seen["received"],
                "seconds": seen["last"] - seen["first"],
                "lost": node.stats()["lost"],
            }

    pipe.send(("result", _run(main())))


def ups_tcp(size: int, count: int) -> dict[str, Any]:
    port = free_port()
    cmd = [
        sys.executable,
        "-m",
        "upscli",
        "broker",
        "--listen",
        f"{HOST}:{port}",
        "--recovery",
        "0",
    ]
    with process(cmd, "TCP-ECB on"):
        sink = Spawned(_ups_sink, (port, size, count), "payload sink")
        source: Spawned | None = None
        try:
            sink.expect("ready", TIMEOUT)
            source = Spawned(_ups_source, (port, size, count), "payload source")
            result: dict[str, Any] = sink.expect("result", TIMEOUT + 10)
            source.expect("sent", TIMEOUT)
        finally:
            for child in (source, sink):
                if child is not None:
                    child.stop(TIMEOUT)
    return _rates(result, size, count)


def _rates(result: dict[str, Any], size: int, count: int) -> dict[str, Any]:
    seconds = max(result["seconds"], 1e-9)
    received = result["received"]
    return {
        **result,
        "sent": count,
        "events_per_s": (received - 1) / seconds if received > 1 else 0.0,
        "mb_per_s": (received - 1) * size / seconds / 1e6 if received > 1 else 0.0,
    }


def run(sizes: tuple[int, ...] = SIZES, mib: float = 256) -> list[dict[str, Any]]:
    """Both transports at every size, raw TCP first; a row per size."""
    rows = []
    for size in sizes:
        count = _count(size, mib)
        raw, ups = raw_tcp(size, count), ups_tcp(size, count)
        ratio = ups["events_per_s"] / raw["events_per_s"] if raw["events_per_s"] else 0.0
        rows.append({"size": size, "count": count, "raw_tcp": raw, "ups": ups, "ratio": ratio})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default=",".join(map(str, SIZES)), help="payload bytes")
    parser.add_argument("--mib", type=float, default=256, help="data per measurement, MiB")
    parser.add_argument("--loop", choices=("uvloop", "asyncio"), default="uvloop",
                        help="UPS's event loop (uvloop when installed)")  # fmt: skip
    parser.add_argument("--json", metavar="PATH", help="also write the rows as JSON here")
    args = parser.parse_args()
    os.environ["UPS_BENCH_LOOP"] = args.loop  # read by the spawned children
    rows = run(tuple(int(s) for s in args.sizes.split(",")), args.mib)
    print(f"{'size':>8}{'events':>9}{'raw ev/s':>11}{'raw MB/s':>10}{'UPS ev/s':>11}"
          f"{'UPS MB/s':>10}{'x raw':>7}{'lost':>6}")  # fmt: skip
    for r in rows:
        raw, ups = r["raw_tcp"], r["ups"]
        lost = r["count"] - ups["received"]
        print(f"{r['size']:>8}{r['count']:>9}{raw['events_per_s']:>11,.0f}{raw['mb_per_s']:>10,.0f}"
              f"{ups['events_per_s']:>11,.0f}{ups['mb_per_s']:>10,.0f}{r['ratio']:>7.2f}"
              f"{lost:>6}")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
