"""Binding throughput of the CAN-ECB: how long until one node holds etags for N new channels?

One CAN-ECB and one node on a python-can virtual bus in this process; the node subscribes to N
channels at once (``asyncio.gather``), each a fresh UID, so every binding is new and must be
made durable in the CAN-ECB's SQLite file before it is announced. Reported: the time to bind
all of them, bindings per second, and the SQLite transactions the CAN-ECB needed (when it
says). Run:

    .venv/bin/python -m ups.benchmarks.can_bind --channels 5000
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

from ups import Node
from ups._canlink import CanLink
from ups.broker._quota import QUOTA
from ups.broker.can_ecb import CanEcb


async def bind(channels: int, concurrency: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        link = CanLink.open("virtual:bench-bind")
        try:
            # one node id creating thousands of bindings is past the CAN-ECB's default quota
            quota = (max(channels, QUOTA[0]), *QUOTA[1:])
            ecb = CanEcb(link, Path(tmp) / "ecb.db", quota=quota)
            await ecb.start()
            await asyncio.sleep(float(getattr(ecb, "_recovery", 0)) + 0.1)  # past recovery
            async with Node(can="virtual:bench-bind", node_id=0xB1D, join_timeout=30) as node:
                names = [f"bench/bind/{i}" for i in range(channels)]
                gate = asyncio.Semaphore(concurrency)

                async def one(name: str) -> None:
                    async with gate:
                        await node.subscribe(name, maxlen=1)

                start = time.perf_counter()
                await asyncio.gather(*(one(n) for n in names))
                elapsed = time.perf_counter() - start
            stats = ecb.stats()
            batches = stats.get("storage_batches", "n/a")
            print(
                f"{channels} channels bound in {elapsed:.2f} s: {channels / elapsed:,.0f}/s, "
                f"{elapsed / channels * 1e3:.3f} ms each; SQLite transactions: {batches}"
            )
            ecb.close()
        finally:
            link.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", type=int, default=5000)
    parser.add_argument("--concurrency", type=int, default=5000, help="requests in flight")
    args = parser.parse_args()
    asyncio.run(bind(args.channels, args.concurrency))


if __name__ == "__main__":
    main()
