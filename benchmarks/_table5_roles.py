"""Table 5's measuring roles, each run in a child process of its own by
``python -m ups.benchmarks.table5 --child ROLE CONFIG`` (see :mod:`benchmarks.table5`): echoes and
pingers on UPS nodes, raw CAN and raw TCP floors, and the rate test's publisher and subscriber.
A role prints JSON lines on stdout and reads commands on stdin.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import struct
import sys
import time
from collections.abc import Callable, Coroutine
from typing import Any

from ups.benchmarks._procs import SETUP_TIMEOUT

MARKER = b"\xff" * 8  # published once by an echo to register as publisher; never a ping
PROBE_STEP = 0xFFFF  # step number of the rate publisher's probes


def _node(net: str, name: str, node_id: int) -> Any:
    """A ``Node`` on ``tcp:HOST:PORT`` (the TCP-ECB) or ``can:INTERFACE:CHANNEL,...``."""
    from ups import Node

    kind, _, where = net.partition(":")
    if kind == "tcp":
        return Node(broker=where, name=name, node_id=node_id)
    return Node(can=where, name=name, node_id=node_id)


def _emit(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


async def _read_line() -> str:
    return await asyncio.to_thread(sys.stdin.readline)


async def child_echo(cfg: dict[str, Any]) -> None:
    """Echo every ping on the pong channel until told to stop (stdin) or ``lifetime`` passes."""
    from ups import Closed

    async with _node(cfg["net"], "table5-echo", cfg["node_id"]) as node:
        sub = await node.subscribe(cfg["ping"], maxlen=4096)
        await node.publish(cfg["pong"], MARKER)  # be known as the pong publisher from the start
        _emit({"event": "ready"})

        async def stop_on_command() -> None:
            await _read_line()
            await sub.close()

        stopper = asyncio.create_task(stop_on_command())
        records: list[tuple[int, int, int, int]] = []
        deadline = time.monotonic() + cfg["lifetime"]
        pong = cfg["pong"]
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = await sub.get_msg(timeout=left)
            except (TimeoutError, Closed):  # Closed: told to stop
                break
            recv_ns = time.time_ns()
            reply_ns = time.time_ns()
            await node.publish(pong, msg.data)
            if len(msg.data) == 8:
                (sent_ns,) = struct.unpack("<Q", msg.data)
                records.append((sent_ns, recv_ns, int(msg.timestamp * 1e9), reply_ns))
        stopper.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await stopper
        _emit({"event": "result", "records": records, "stats": node.stats()})


async def child_ping(cfg: dict[str, Any]) -> None:
    """Probe until a round trip works, then time ``warmup`` + ``count`` round trips."""
    async with _node(cfg["net"], "table5-ping", cfg["node_id"]) as node:
        sub = await node.subscribe(cfg["pong"], maxlen=4096)
        ping = cfg["ping"]

        async def one(timeout: float) -> tuple[int, int, int, int] | None:
            payload = struct.pack("<Q", time.time_ns())
            start = time.perf_counter_ns()
            await node.publish(ping, payload)
            deadline = time.monotonic() + timeout
            while (left := deadline - time.monotonic()) > 0:
                try:
                    msg = await sub.get_msg(timeout=left)
                except TimeoutError:
                    return None
                if msg.data == payload:
                    rtt = time.perf_counter_ns() - start
                    back_ns = time.time_ns()
                    sent_ns = struct.unpack("<Q", payload)[0]
                    return sent_ns, back_ns, int(msg.timestamp * 1e9), rtt
            return None

        t0 = time.monotonic()
        probes = 0
        while True:
            probes += 1
            if await one(cfg["probe_timeout"]) is not None:
                break
            if time.monotonic() - t0 > cfg["setup_timeout"]:
                _emit({"event": "error", "error": f"no round trip after {probes} probes"})
                return
        setup_s = time.monotonic() - t0
        samples: list[tuple[int, int, int, int]] = []
        lost = 0
        gap = cfg["gap"]
        for i in range(cfg["warmup"] + cfg["count"]):
            if gap:
                await asyncio.sleep(gap)
            result = await one(2.0)
            if result is None:
                lost += 1
                if lost > max(10, cfg["count"] // 10):
                    break
            elif i >= cfg["warmup"]:
                samples.append(result)
        _emit(
            {
                "event": "result",
                "samples": samples,
                "probes": probes,
                "setup_s": setup_s,
                "lost": lost,
                "stats": node.stats(),
            }
        )


def _raw_can_ids() -> tuple[int, int]:
    from ups import _canproto as p

    # Not management frames (a real TxNode field, an etag above the reserved ones) and on no
    # etag the CAN-ECB hands out this early: every UPS handler on the bus ignores them.
    return p.make_id(0xFF, 0x7E, 0x3FFD), p.make_id(0xFF, 0x7E, 0x3FFE)


def child_raw_can_echo(cfg: dict[str, Any]) -> None:
    """The floor of a CAN hop: python-can's blocking recv/send, no middleware."""
    import can

    from ups._canlink import open_bus

    ping_id, pong_id = _raw_can_ids()
    bus = open_bus(cfg["bus"])
    try:
        _emit({"event": "ready"})
        deadline = time.monotonic() + cfg["lifetime"]
        idle = 0.0
        while time.monotonic() < deadline and idle < 3.0:
            frame = bus.recv(0.5)
            if frame is None:
                idle += 0.5
                continue
            idle = 0.0
            if frame.arbitration_id == ping_id and frame.is_extended_id:
                bus.send(can.Message(arbitration_id=pong_id, data=frame.data, is_extended_id=True))
    finally:
        bus.shutdown()


def child_raw_can_ping(cfg: dict[str, Any]) -> None:
    import can

    from ups._canlink import open_bus

    ping_id, pong_id = _raw_can_ids()
    bus = open_bus(cfg["bus"])

    def one(timeout: float) -> int | None:
        payload = struct.pack("<Q", time.time_ns())
        start = time.perf_counter_ns()
        bus.send(can.Message(arbitration_id=ping_id, data=payload, is_extended_id=True))
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            frame = bus.recv(left)
            if frame is not None and frame.arbitration_id == pong_id and frame.data == payload:
                return time.perf_counter_ns() - start
        return None

    try:
        _raw_ping_loop(one, cfg)
    finally:
        bus.shutdown()


def _raw_ping_loop(one: Callable[[float], int | None], cfg: dict[str, Any]) -> None:
    t0 = time.monotonic()
    probes = 0
    while True:
        probes += 1
        if one(cfg["probe_timeout"]) is not None:
            break
        if time.monotonic() - t0 > cfg["setup_timeout"]:
            _emit({"event": "error", "error": f"no round trip after {probes} probes"})
            return
    rtts: list[int] = []
    lost = 0
    for i in range(cfg["warmup"] + cfg["count"]):
        if cfg["gap"]:
            time.sleep(cfg["gap"])
        rtt = one(2.0)
        if rtt is None:
            lost += 1
            if lost > max(10, cfg["count"] // 10):
                break
        elif i >= cfg["warmup"]:
            rtts.append(rtt)
    samples = [(0, 0, 0, rtt) for rtt in rtts]
    _emit({"event": "result", "samples": samples, "probes": probes, "lost": lost})


def child_raw_tcp_echo(cfg: dict[str, Any]) -> None:
    """The floor of a TCP hop: a blocking socket echoing 8-byte messages, no middleware."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        server.settimeout(SETUP_TIMEOUT)
        _emit({"event": "ready", "port": server.getsockname()[1]})
        conn, _ = server.accept()
        with conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(cfg["lifetime"])
            while data := _recv_exact(conn, 8):
                conn.sendall(data)


def _recv_exact(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        if not chunk:
            return b""
        data += chunk
    return data


def child_raw_tcp_ping(cfg: dict[str, Any]) -> None:
    with socket.create_connection(("127.0.0.1", cfg["port"]), timeout=10) as conn:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        def one(timeout: float) -> int | None:
            payload = struct.pack("<Q", time.time_ns())
            start = time.perf_counter_ns()
            conn.sendall(payload)
            back = _recv_exact(conn, 8)
            return time.perf_counter_ns() - start if back == payload else None

        _raw_ping_loop(one, cfg)


async def child_rate_sub(cfg: dict[str, Any]) -> None:
    """Count the events of each step; answer ``report STEP K`` on stdin with the counts."""
    async with _node(cfg["net"], "table5-ratesub", cfg["node_id"]) as node:
        sub = await node.subscribe(cfg["channel"], maxlen=1 << 21)
        _emit({"event": "ready"})
        steps: dict[int, dict[str, Any]] = {}
        path_seen = False

        async def receive() -> None:
            nonlocal path_seen
            while True:
                msg = await sub.get_msg()
                now = time.perf_counter()
                seq, step = struct.unpack("<IH2x", msg.data)
                if step == PROBE_STEP:
                    if not path_seen:
                        path_seen = True
                        _emit({"event": "path"})
                    continue
                st = steps.get(step)
                if st is None:
                    st = steps[step] = {"n": 0, "seen": set(), "first": now, "last": now, "ooo": 0}
                    st["prev"] = -1
                st["n"] += 1
                st["seen"].add(seq)
                st["last"] = now
                if seq < st["prev"]:
                    st["ooo"] += 1
                st["prev"] = seq

        receiver = asyncio.create_task(receive())
        try:
            while line := (await _read_line()).split():
                if line[0] != "report":
                    break
                step, expect = int(line[1]), int(line[2])
                t0 = time.perf_counter()
                while time.perf_counter() - t0 < 15.0:  # bounded: 15 s at most per step
                    st = steps.get(step)
                    if st is not None and st["n"] >= expect:
                        break
                    last = st["last"] if st is not None else t0
                    if time.perf_counter() - max(last, t0) > 1.0:  # 1 s without an event
                        break
                    await asyncio.sleep(0.02)
                st = steps.get(step, {"n": 0, "seen": set(), "first": 0.0, "last": 0.0, "ooo": 0})
                _emit(
                    {
                        "event": "report",
                        "received": st["n"],
                        "unique": len(st["seen"]),
                        "out_of_order": st["ooo"],
                        "span_s": st["last"] - st["first"],
                        "stats": node.stats(),
                    }
                )
        finally:
            receiver.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await receiver


async def child_rate_pub(cfg: dict[str, Any]) -> None:
    """Probe (every 20 ms) until the first ``run STEP RATE K PACING``; then K events per run.

    Pacing ``timer``: whatever is due goes at once, then the loop sleeps until the next event
    is due (uvloop's timers have 1 ms resolution, so events leave in bursts of RATE/1000).
    Pacing ``spin``: each event leaves at its own time, busy-waiting in between, as frames
    spaced by a real bus (this costs the publisher a whole CPU).
    """
    async with _node(cfg["net"], "table5-ratepub", cfg["node_id"]) as node:
        channel = cfg["channel"]
        await node.publish(channel, struct.pack("<IH2x", 0, PROBE_STEP))
        _emit({"event": "ready"})

        async def probe() -> None:
            for seq in range(int(SETUP_TIMEOUT / 0.02)):
                await node.publish(channel, struct.pack("<IH2x", seq, PROBE_STEP))
                await asyncio.sleep(0.02)

        prober: asyncio.Task[None] | None = asyncio.create_task(probe())
        while line := (await _read_line()).split():
            if prober is not None:
                prober.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await prober
                prober = None
            if line[0] != "run":
                break
            step, rate, count, spin = int(line[1]), float(line[2]), int(line[3]), line[4] == "spin"
            failed0 = node.stats().get("tx_failed", 0)
            pack = struct.Struct("<IH2x").pack
            start = time.perf_counter()
            if rate <= 0:  # flat out, letting the loop run every 64 events
                for seq in range(count):
                    await node.publish(channel, pack(seq, step))
                    if seq % 64 == 63:
                        await asyncio.sleep(0)
            elif spin:
                clock = time.perf_counter
                for seq in range(count):
                    due = start + seq / rate
                    while clock() < due:
                        pass
                    await node.publish(channel, pack(seq, step))
                    if seq % 256 == 255:  # read our own echoes now and then
                        await asyncio.sleep(0)
            else:  # on schedule: whatever is due goes at once, then sleep until the next
                seq = 0
                while seq < count:
                    due = min(count, int((time.perf_counter() - start) * rate) + 1)
                    while seq < due:
                        await node.publish(channel, pack(seq, step))
                        seq += 1
                    ahead = seq / rate - (time.perf_counter() - start)
                    await asyncio.sleep(max(0.0, ahead))
            duration = time.perf_counter() - start
            _emit(
                {
                    "event": "done",
                    "sent": count,
                    "duration_s": duration,
                    "tx_failed": node.stats().get("tx_failed", 0) - failed0,
                }
            )


CHILDREN: dict[str, Callable[[dict[str, Any]], Any]] = {
    "echo": child_echo,
    "ping": child_ping,
    "raw_can_echo": child_raw_can_echo,
    "raw_can_ping": child_raw_can_ping,
    "raw_tcp_echo": child_raw_tcp_echo,
    "raw_tcp_ping": child_raw_tcp_ping,
    "rate_sub": child_rate_sub,
    "rate_pub": child_rate_pub,
}


def run_child(role: str, cfg: dict[str, Any]) -> None:
    if cfg.get("cpu") is not None:
        os.sched_setaffinity(0, {cfg["cpu"]})
    import can

    can.util.set_logging_level("warning")
    result = CHILDREN[role](cfg)
    if asyncio.iscoroutine(result):
        run_async(result)


def run_async(coro: Coroutine[Any, Any, None]) -> None:
    """On uvloop when installed, as ``ups`` itself runs."""
    try:
        import uvloop
    except ImportError:
        asyncio.run(coro)
        return
    uvloop.run(coro)
