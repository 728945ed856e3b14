"""The blocking facade, from a plain thread with no event loop of its own."""

from __future__ import annotations

import asyncio
import threading

import pytest

from ups import BlockingNode, BrokerUnavailable, PayloadTooLarge, Unschedulable
from ups.broker.can_ecb import CanEcb


async def test_blocking_nodes_talk_through_the_ecb(bus: str, ecb: CanEcb) -> None:
    def script() -> list[bytes]:
        with BlockingNode(can=bus, node_id=1) as a, BlockingNode(can=bus, node_id=2) as b:
            sub = b.subscribe("speed")
            a.set_priority("speed", 3)
            a.publish("speed", b"\x01")
            a.publish("speed", b"\x02")
            first = sub.get_msg(timeout=5)
            assert first.priority == 3
            with pytest.raises(PayloadTooLarge):
                a.publish("speed", bytes(65536))
            got = [first.data, b.get_msg(timeout=5).data]
            sub.close()
            assert list(sub) == []  # iteration ends once closed
            assert a.stats()["sent"] == 2
            return got

    assert await asyncio.to_thread(script) == [b"\x01", b"\x02"]
    assert not [t for t in threading.enumerate() if t.name == "ups-blocking-loop"]


def test_blocking_node_without_broker_fails_cleanly(bus: str) -> None:
    with pytest.raises(BrokerUnavailable):
        BlockingNode(can=bus, node_id=1, join_timeout=0.2)
    assert not [t for t in threading.enumerate() if t.name == "ups-blocking-loop"]


async def test_blocking_nodes_declare_real_time_channels(bus: str, ecb: CanEcb) -> None:
    def script() -> int:
        with BlockingNode(can=bus, node_id=1) as a:
            priority = a.declare("brake", period_ms=10, deadline_ms=5, size_bytes=2)
            with pytest.raises(Unschedulable):  # 0.1 ms: shorter than one 8-byte frame
                a.declare("steer", period_ms=1, deadline_ms=0.1, size_bytes=8)
            a.publish("brake", b"\x01\x02", wait=True)
            return priority

    assert 0x02 <= await asyncio.to_thread(script) <= 0xFF
