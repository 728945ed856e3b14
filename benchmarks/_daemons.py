"""Resident memory of UPS's daemons and of an idle TCP node, each a process of its own.

Each one is started, waited for (its "ready" line, every wait bounded), given time to settle
(its RSS read until it stops growing), and stopped by its PID.
"""

from __future__ import annotations

import os
import sys
import time

from ups.benchmarks._procs import free_port, process

_IDLE_NODE = """
import asyncio, sys
from ups import Node
async def main():
    async with Node(broker=sys.argv[1], name="bench-idle", node_id=0xB1D1E) as node:
        await node.subscribe("bench/idle")
        print("idle node ready", file=sys.stderr, flush=True)
        await asyncio.sleep(60)
asyncio.run(main())
"""


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise ValueError(f"no VmRSS for {pid}")


def _settled(pid: int) -> float:
    """RSS once two readings 0.5 s apart agree within 0.1 MB (at most 5 s)."""
    last = rss_mb(pid)
    for _ in range(10):
        time.sleep(0.5)
        now = rss_mb(pid)
        if abs(now - last) < 0.1:
            return now
        last = now
    return last


def daemon_rss() -> dict[str, float]:
    """MB of RSS: the TCP-ECB, the CAN-ECB, the gateway (hosting its CAN-ECB), an idle TCP
    node, and a bare interpreter (the floor)."""
    ups = [sys.executable, "-m", "upscli"]
    port = free_port()
    address = f"127.0.0.1:{port}"
    bus = f"virtual:bench-rss-{os.getpid()}"
    out: dict[str, float] = {}
    with process(
        [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(60)"], "up"
    ) as bare:
        out["python_bare"] = _settled(bare.pid)
    with process([*ups, "broker", "--listen", address, "--recovery", "0"], "TCP-ECB on") as ecb:
        out["tcp_ecb"] = _settled(ecb.pid)
        with process([sys.executable, "-c", _IDLE_NODE, address], "idle node ready") as node:
            out["idle_tcp_node"] = _settled(node.pid)
        with process([*ups, "gateway", "--can", bus, "--broker", address], "between") as gw:
            out["gateway"] = _settled(gw.pid)
    with process([*ups, "can-broker", "--can", bus + "-ecb"], "CAN-ECB on") as can_ecb:
        out["can_ecb"] = _settled(can_ecb.pid)
    return out
