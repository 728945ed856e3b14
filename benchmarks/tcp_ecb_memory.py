"""Memory of the TCP-ECB holding many nodes and channels.

Starts ``ups broker`` (a process of its own), connects ``--nodes`` TCP nodes from this process,
each subscribing to ``--channels`` / ``--nodes`` channels of its own, and reports the broker's
resident memory (VmRSS) before and after, and per node and channel. Run:

    .venv/bin/python -m ups.benchmarks.tcp_ecb_memory --nodes 1000 --channels 10000
"""

from __future__ import annotations

import argparse
import asyncio
import resource
import sys
from pathlib import Path

from ups import Node
from ups.benchmarks._procs import process


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return -1


async def measure(pid: int, address: str, nodes: int, channels: int) -> None:
    await asyncio.sleep(0.5)
    before = rss_kib(pid)
    each = max(1, channels // nodes)
    started: list[Node] = []
    try:
        for i in range(nodes):
            node = Node(broker=address, node_id=0x10000 + i, name=f"m{i}", join_timeout=30)
            await node.start()
            started.append(node)
            await node.subscribe(*(f"mem/{i}/{c}" for c in range(each)), maxlen=1)
        await asyncio.sleep(1.0)
        after = rss_kib(pid)
        grown = after - before
        print(
            f"TCP-ECB with {nodes} nodes and {nodes * each} channels: RSS {before / 1024:.1f} "
            f"-> {after / 1024:.1f} MiB (+{grown / 1024:.1f} MiB: {grown / nodes:.1f} KiB "
            f"per node, {grown * 1024 / (nodes * each):.0f} B per channel)"
        )
    finally:
        await asyncio.gather(*(n.close() for n in started))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=1000)
    parser.add_argument("--channels", type=int, default=10_000)
    args = parser.parse_args()
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))  # two sockets per node here
    cmd = [sys.executable, "-m", "upscli", "broker", "--listen", "127.0.0.1:0", "--recovery", "0"]
    with process(cmd, r"TCP-ECB on (127\.0\.0\.1:\d+)") as broker:
        assert broker.found is not None
        asyncio.run(measure(broker.pid, broker.found.group(1), args.nodes, args.channels))


if __name__ == "__main__":
    main()
