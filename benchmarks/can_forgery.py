"""What a forger on a CAN bus achieves, measured: the figures of issue 32's note.

On python-can ``virtual`` buses in this process, with real nodes and the real CAN-ECB; the forger
sends raw frames. It uses only what every version has (no option of the new code), so the same
script gives the figures before and after the change:

- etags a rogue pair of node ids takes with 16,400 PUB_BINDs of made-up channels, and whether a
  node can then bind 300 new channels;
- how long a forged Grant's effect lasts: on a best-effort channel (no declaration), and on a
  declared stream (another priority): the span during which the node's events go out at the
  forged priority, within a window of ``--window`` seconds after the forged frame;
- how long a forged TxNodesFull or Failed's effect lasts: three joiners, each told so when the
  CAN-ECB offers it a TxNode: how many joins fail, and how long the joins take against the same
  three joining with nobody forging.

    .venv/bin/python -m ups.benchmarks.can_forgery
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import tempfile
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import can

from ups import Node, name_to_uid
from ups import _canproto as p
from ups._canlink import CanLink
from ups._errors import DecodeError
from ups.broker.can_ecb import CanEcb

JOINERS = [0x0A11_0001, 0x0A11_0002, 0x0A11_0003]


@contextlib.asynccontextmanager
async def bus_with_ecb(name: str, tmp: Path) -> AsyncIterator[tuple[str, CanEcb, can.BusABC]]:
    """A virtual bus, its CAN-ECB (0.1 s recovery) and a raw bus to forge on."""
    bus = f"virtual:forgery-{name}"
    raw = can.Bus(interface="virtual", channel=bus.partition(":")[2])
    link = CanLink.open(bus)
    ecb = CanEcb(link, tmp / f"{name}.db", recovery=0.1)
    try:
        await ecb.start()  # nodes knock: a census follows the recovery
        yield bus, ecb, raw
    finally:
        ecb.close()
        link.close()
        raw.shutdown()


def forge(raw: can.BusABC, msg: p.Management) -> float:
    can_id, data = p.encode(msg)
    raw.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))
    return time.time()


async def rogue_pair(tmp: Path) -> str:
    async with (
        bus_with_ecb("rogues", tmp) as (bus, ecb, raw),
        Node(can=bus, node_id=0xBAD1) as a,
        Node(can=bus, node_id=0xBAD2) as b,
    ):
        before = ecb.counters["requests"]
        for rogue in (a, b):
            txnode = rogue.stats()["txnode"]
            for i in range(8200):
                forge(raw, p.Request(p.PUB_BIND, txnode, (0xBAD0 + txnode) << 32 | i))
        deadline = time.monotonic() + 120
        while ecb.counters["requests"] < before + 16_400 or ecb._etags._pending:
            if time.monotonic() > deadline:
                break
            await asyncio.sleep(0.05)
        taken = len(ecb.etags)
        async with Node(can=bus, node_id=0x600D) as good:
            try:
                await good.subscribe(*[f"robot/{i}" for i in range(300)])
                after = "a node then binds 300 new channels"
            except Exception as exc:  # what the node says is the figure
                after = f"a node then binding 300 new channels: {type(exc).__name__}: {exc}"
    return f"rogue pair (16,400 PUB_BINDs): {taken} etags taken of 12,272 in class 0; {after}"


async def forged_grant(tmp: Path, declared: bool, window: float) -> str:
    """The span of events sent at the forged priority after one forged Grant."""
    async with (
        bus_with_ecb(f"grant-{declared}", tmp) as (bus, ecb, raw),
        Node(can=bus, node_id=1) as pub,
        Node(can=bus, node_id=2) as sub_node,
    ):
        sub = await sub_node.subscribe("x", maxlen=1 << 16)
        if declared:
            good = await pub.declare("x", period_ms=10, deadline_ms=10, size_bytes=1)
            forged = 0x70
        else:
            await pub.publish("x", b"\x00")
            good, forged = p.DEFAULT_PRIORITY, 0x02
        etag, txnode = ecb.etags[name_to_uid("x")], pub.stats()["txnode"]
        await asyncio.sleep(0.6)  # past the declaration's own verdicts
        while sub.pending:
            await sub.get_msg(timeout=0)
        while raw.recv(0) is not None:  # what came before the forgery
            pass
        sent_at = forge(raw, p.Grant(etag, txnode, forged))
        end = time.monotonic() + window
        while time.monotonic() < end:
            await pub.publish("x", b"\x01")
            await asyncio.sleep(0.001)
        await asyncio.sleep(0.1)  # the last events arrive (a bounded drain, not a sync)
        wrong: list[float] = []
        while sub.pending:
            msg = await sub.get_msg(timeout=0)
            if msg.priority != good:
                wrong.append(msg.timestamp)
        corrected = None  # when the CAN-ECB's answer to the forged Grant was on the bus
        while (frame := raw.recv(0)) is not None and corrected is None:
            with contextlib.suppress(DecodeError):
                if p.is_management(frame.arbitration_id) and isinstance(
                    p.decode(frame.arbitration_id, bytes(frame.data)), p.Grant | p.Refuse
                ):
                    corrected = frame.timestamp - sent_at
    what = "declared stream" if declared else "best-effort channel"
    answer = "gave no answer" if corrected is None else f"answered after {corrected * 1000:.1f} ms"
    if not wrong:
        return f"forged Grant on a {what}: no event at the forged priority; the CAN-ECB {answer}"
    span = max(wrong) - sent_at
    lasting = f", still at the end of the {window:g} s window" if span > window - 0.2 else ""
    return (
        f"forged Grant on a {what}: events at the forged priority for {span * 1000:.1f} ms "
        f"({len(wrong)} events{lasting}); the CAN-ECB {answer}"
    )


def refusal_forger(bus: str, make: Callable[[int], p.Management]) -> CanLink:
    link = CanLink.open(bus)

    def on_frame(frame: can.Message) -> None:
        if not frame.is_extended_id or not p.is_management(frame.arbitration_id):
            return
        with contextlib.suppress(DecodeError):
            msg = p.decode(frame.arbitration_id, bytes(frame.data))
            if isinstance(msg, p.Offer) and msg.node_id in JOINERS:
                can_id, data = p.encode(make(msg.node_id))
                link.send(can_id, data)

    link.add_handler(on_frame, None)
    link.start()
    return link


async def join_three(bus: str) -> tuple[int, float]:
    joiners = [Node(can=bus, node_id=i, join_timeout=15) for i in JOINERS]
    start = time.monotonic()
    try:
        results = await asyncio.gather(*(n.start() for n in joiners), return_exceptions=True)
        return sum(isinstance(r, Exception) for r in results), time.monotonic() - start
    finally:
        for node in joiners:
            await node.close()


async def forged_refusal(tmp: Path, kind: str) -> str:
    async with bus_with_ecb(f"plain-{kind}", tmp) as (bus, _, _raw):
        _, plain = await join_three(bus)
    make: Callable[[int], p.Management] = p.TxNodesFull if kind == "TxNodesFull" else p.Failed
    async with bus_with_ecb(f"refusal-{kind}", tmp) as (bus, _, _raw):
        forger = refusal_forger(bus, make)
        try:
            failed, took = await join_three(bus)
        finally:
            forger.close()
    return (
        f"forged {kind} at each Offer: {failed} of 3 joins failed; the joins took "
        f"{took * 1000:.0f} ms ({plain * 1000:.0f} ms with nobody forging)"
    )


async def main(window: float) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print(await rogue_pair(folder))
        print(await forged_grant(folder, declared=False, window=window))
        print(await forged_grant(folder, declared=True, window=window))
        for kind in ("TxNodesFull", "Failed"):
            print(await forged_refusal(folder, kind))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--window", type=float, default=2.0, help="seconds watched after a forgery")
    asyncio.run(main(parser.parse_args().window))
