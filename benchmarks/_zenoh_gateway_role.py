"""The gateway role of the Zenoh benchmark's steps (``_zenoh_steps.py``): a ``Gateway`` on a
virtual bus in its process, onto Zenoh or TCP/IP, or the floor (a thread that puts each frame's
data on the channel's key, plain zenoh); a raw python-can bus in the same process blasts the
frames, as fast as python-can sends them.

Every wait here is bounded; the harness kills a role that does not end by its PID.
"""

from __future__ import annotations

import asyncio
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from ups.benchmarks._zenoh_clients import (
    DATA,
    IDS,
    PROBE_STEP,
    SETUP_TIMEOUT,
    TAG,
    pipe_recv,
    raw_publisher,
    raw_session,
    run,
    until,
)

RECOVERY = 0.2  #: the hosted CAN-ECB's recovery window: the bus is this process's own, no node
#: is on it before the gateway (the window is setup, before anything is measured)


def _blaster(bus: Any, can_id: int) -> Callable[[int, int], dict[str, float]]:
    """``blast(step, count)``: ``count`` frames of ``step`` onto the bus as fast as python-can
    sends them, before the gateway reads any: this thread keeps the interpreter meanwhile
    (``sys.setswitchinterval``), so the gateway then drains a full receive queue, alone."""
    import can

    def blast(step: int, count: int) -> dict[str, float]:
        frames = [can.Message(arbitration_id=can_id, data=TAG.pack(i, step), is_extended_id=True)
                  for i in range(count)]  # fmt: skip
        send, interval = bus.send, sys.getswitchinterval()
        sys.setswitchinterval(min(10.0, 1.0 + count * 20e-6))
        time.sleep(0.05)  # threads already waiting for the interpreter: theirs is the old one
        t0 = time.perf_counter()
        try:
            for frame in frames:
                send(frame)
        finally:
            sys.setswitchinterval(interval)
        end = time.perf_counter()
        return {"sent": count, "seconds": end - t0, "end": end, "cpu_s": time.process_time()}

    return blast


def gateway(cfg: dict[str, Any], conn: Connection) -> None:
    """A ``Gateway`` (``ip``: ``zenoh`` or ``tcp``) on a virtual bus in this process, or the
    floor (``bridge``: a thread that reads the bus and puts each frame's data on the channel's
    key, plain zenoh). A raw python-can bus on the same virtual channel blasts the frames."""
    import can

    from ups import _canproto as p
    from ups import name_to_uid

    raw = can.Bus(interface="virtual", channel=cfg["bus"])
    try:
        if cfg["ip"] == "bridge":
            _bridge(cfg, conn, raw, name_to_uid(DATA), p.make_id(0x80, 0x05, p.FIRST_ETAG))
        else:
            run(_gateway(cfg, conn, raw))
    finally:
        raw.shutdown()


def _serve_blasts(conn: Connection, raw: Any, can_id: int, stats: Callable[[], Any]) -> None:
    """Answer ``("blast", step, count)`` and ``("stats",)`` (with this process's CPU time) until
    ``("quit",)``."""
    conn.send(("ready", None))
    blast = _blaster(raw, can_id)
    while (cmd := pipe_recv(conn))[0] != "quit":
        if cmd[0] == "blast":
            conn.send(("done", blast(cmd[1], cmd[2])))
        else:
            conn.send(("stats", {**stats(), "cpu_s": time.process_time()}))


def _bridge(cfg: dict[str, Any], conn: Connection, raw: Any, uid: int, can_id: int) -> None:
    import can

    bus = can.Bus(interface="virtual", channel=cfg["bus"])
    session = raw_session(cfg["endpoint"])
    stop, forwarded = threading.Event(), [0]
    try:
        pub = raw_publisher(session, f"ups/{uid:016x}", cfg)

        def forward() -> None:
            recv, put = bus.recv, pub.put
            while not stop.is_set():
                frame = recv(0.05)
                if frame is not None:
                    put(bytes(frame.data))
                    forwarded[0] += 1

        thread = threading.Thread(target=forward, name="bench-bridge", daemon=True)
        thread.start()
        _serve_blasts(conn, raw, can_id, lambda: {"to_zenoh": forwarded[0]})
        stop.set()
        thread.join(1.0)
    finally:
        session.close()
        bus.shutdown()


async def _gateway(cfg: dict[str, Any], conn: Connection, raw: Any) -> None:
    from ups import Node
    from ups._canlink import CanLink
    from ups.gateway import Gateway

    link = CanLink.open(f"virtual:{cfg['bus']}")
    zenoh, broker = (cfg["endpoint"], None) if cfg["ip"] == "zenoh" else (None, cfg["endpoint"])
    gw = Gateway(link, broker, zenoh=zenoh, db=cfg["db"], node_id=IDS["gateway"],
                 bitrate=1_000_000, name="bench-zgateway", join_timeout=SETUP_TIMEOUT,
                 recovery=RECOVERY)  # fmt: skip
    async with gw:
        side = gw.side
        async with Node(can=link, node_id=IDS["canpub"], name="bench-zcanpub") as pub:
            marker = TAG.pack(0, PROBE_STEP)
            await pub.publish(DATA, marker)  # binds; the gateway forwards once it matches
            await until(lambda: gw.stats()[f"forwarding_to_{side}"] >= 1, "no forwarding")
            deadline = time.monotonic() + SETUP_TIMEOUT
            while True:  # the publisher's CAN id, as any node on the bus sees it
                frame = await asyncio.to_thread(raw.recv, 0.1)
                if frame is not None and bytes(frame.data) == marker:
                    can_id = frame.arbitration_id
                    break
                if time.monotonic() > deadline:
                    raise TimeoutError("the publisher's event never reached the bus")
        # the publisher node is gone from this process; its binding stays: from here on the
        # raw bus sends its frames, as a node elsewhere on the bus would (from another thread)
        await asyncio.to_thread(_serve_blasts, conn, raw, can_id, gw.stats)
