"""TLS (and TLS with an ACL) against plain TCP for UPS itself, in the same run: round trip and
one-way throughput.

A TCP-ECB and two nodes in this process on loopback (one event loop, so absolute figures are
lower than across processes; the ratio is the point). Round trip: node A publishes a ping,
node B answers with a pong, ``--roundtrips`` times. Throughput: A publishes ``--messages``
8-byte events with backpressure (``wait=True``), B counts them. The ACL run adds the broker's
access control and the subscribers' check of each publisher's identity. Run:

    .venv/bin/python -m ups.benchmarks.tcp_tls
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ups import Node, Tls
from ups.broker._acl import Acl
from ups.broker.tcp_ecb import TcpEcb


def make_fleet(folder: Path) -> None:
    for args in (["ca", str(folder)], *(["issue", str(folder), n] for n in ("broker", "a", "b"))):
        subprocess.run([sys.executable, "-m", "upscli", "certs", *args], check=True,
                       capture_output=True)  # fmt: skip


_ACL = """
[identity.a]
publish = ["bench/*"]
subscribe = ["bench/pong"]
[identity.b]
publish = ["bench/pong"]
subscribe = ["bench/ping", "bench/flow"]
"""


async def run(
    tls: dict[str, Tls] | None, roundtrips: int, messages: int, acl: Acl | None = None
) -> tuple[float, float]:
    ecb = TcpEcb("127.0.0.1", 0, recovery=0, tls=tls["broker"] if tls else None, acl=acl)
    await ecb.start()
    address = f"127.0.0.1:{ecb.port}"
    try:
        async with (
            Node(broker=address, node_id=0xA, tls=tls["a"] if tls else None) as a,
            Node(broker=address, node_id=0xB, tls=tls["b"] if tls else None) as b,
        ):
            pongs = await a.subscribe("bench/pong", maxlen=messages)
            pings = await b.subscribe("bench/ping", "bench/flow", maxlen=messages)

            async def echo() -> None:
                async for msg in pings:
                    if msg.channel.name == "bench/ping":
                        await b.publish("bench/pong", msg.data)

            echoer = asyncio.create_task(echo())
            for _ in range(200):  # warm-up: links up
                await a.publish("bench/ping", b"x")
                await pongs.get_msg(timeout=5)
            times = []
            for _ in range(roundtrips):
                start = time.perf_counter()
                await a.publish("bench/ping", b"x")
                await pongs.get_msg(timeout=5)
                times.append(time.perf_counter() - start)
            echoer.cancel()
            got = 0
            start = time.perf_counter()
            for _ in range(messages):
                await a.publish("bench/flow", b"12345678", wait=True)
            while got < messages:
                await pings.get_msg(timeout=10)
                got += 1
            rate = messages / (time.perf_counter() - start)
            return statistics.median(times) * 1e6, rate
    finally:
        await ecb.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--roundtrips", type=int, default=5000)
    parser.add_argument("--messages", type=int, default=100_000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        make_fleet(folder)
        tls = {n: Tls(folder / "ca.crt", folder / f"{n}.crt", folder / f"{n}.key")
               for n in ("broker", "a", "b")}  # fmt: skip
        plain = asyncio.run(run(None, args.roundtrips, args.messages))
        secure = asyncio.run(run(tls, args.roundtrips, args.messages))
        guarded = asyncio.run(run(tls, args.roundtrips, args.messages, Acl.parse(_ACL)))
    for label, (rtt, rate) in (("plain TCP", plain), ("TLS", secure), ("TLS + ACL", guarded)):
        print(f"{label:10} round trip p50 {rtt:6.1f} us, throughput {rate:9,.0f} events/s")
    for label, (rtt, rate) in (("TLS", secure), ("TLS + ACL", guarded)):
        print(f"{label}/plain: round trip {rtt / plain[0]:.2f}x, throughput {rate / plain[1]:.2f}x")


if __name__ == "__main__":
    main()
