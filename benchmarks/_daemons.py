"""Resident memory of UPS's daemons and of an idle TCP node, each a process of its own.

Each one is started, waited for (its "ready" line, every wait bounded), given time to settle
(its RSS read until it stops growing), and stopped by its PID.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
START_TIMEOUT = 20.0
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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise ValueError(f"no VmRSS for {pid}")


@contextlib.contextmanager
def process(cmd: list[str], ready: str) -> Iterator[subprocess.Popen[bytes]]:
    """``cmd`` started with its stderr in a file, once it logged ``ready``; stopped after."""
    with tempfile.TemporaryDirectory(prefix="ups-bench-") as tmp:
        log = Path(tmp, "log")
        with log.open("wb") as out:
            proc = subprocess.Popen(cmd, cwd=ROOT, stdin=subprocess.DEVNULL, stdout=out, stderr=out)
        try:
            deadline = time.monotonic() + START_TIMEOUT
            while ready not in log.read_text(errors="replace"):
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"{cmd[2:4]} did not start: {log.read_text()[-500:]}")
                time.sleep(0.05)
            yield proc
        finally:
            proc.terminate()
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


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
