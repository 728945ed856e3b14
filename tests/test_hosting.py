"""Hosting a broker in the program's own event loop: broker.hosted_can_ecb, hosted_tcp_ecb."""

from __future__ import annotations

from pathlib import Path

from ups import Node, broker


async def test_a_virtual_bus_with_its_can_ecb_in_process(bus: str, tmp_path: Path) -> None:
    async with (
        broker.hosted_can_ecb(bus, tmp_path / "ecb.db", recovery=0.1) as ecb,
        Node(can=bus, node_id=1) as a,
        Node(can=bus, node_id=2) as b,
    ):
        sub = await b.subscribe("hosted")
        await a.publish("hosted", b"\x01")
        assert (await sub.get_msg(timeout=5)).data == b"\x01"
        assert ecb.stats()["txnodes"] == 2


async def test_a_tcp_ecb_in_process() -> None:
    async with (
        broker.hosted_tcp_ecb(recovery=0) as ecb,
        Node(broker=f"127.0.0.1:{ecb.port}", node_id=1) as a,
        Node(broker=f"127.0.0.1:{ecb.port}", node_id=2) as b,
    ):
        sub = await b.subscribe("hosted")
        await a.publish("hosted", b"\x02")
        assert (await sub.get_msg(timeout=5)).data == b"\x02"
