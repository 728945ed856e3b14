"""Real-time channels: admission control by a live CAN-ECB, on virtual buses."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from ups import ConfigError, Node, Unschedulable, name_to_uid
from ups import _canproto as p
from ups.broker._admission import RT_FIRST, RT_LAST
from ups.broker.can_ecb import CanEcb

from .conftest import eventually, running_ecb

# At 125 kbit/s a worst-case 8-byte frame with a 29-bit identifier (160 bits) takes 1.28 ms.
SLOW = 125_000


@pytest.fixture
async def slow_ecb(bus: str, tmp_path: Path) -> AsyncIterator[CanEcb]:
    async with running_ecb(bus, tmp_path / "ecb.db", bitrate=SLOW, recovery=0.1) as ecb:
        yield ecb


async def test_declared_channel_is_admitted_and_published_at_its_priority(
    bus: str, slow_ecb: CanEcb
) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as sub:
        s = await sub.subscribe("brake", "log")
        priority = await pub.declare("brake", period_ms=10, deadline_ms=5, size_bytes=1)
        assert RT_FIRST <= priority <= RT_LAST
        await pub.publish("brake", b"\x01")
        await pub.publish("log", b"\x02")  # best effort
        brake, log = await s.get_msg(timeout=5), await s.get_msg(timeout=5)
        assert brake.priority == priority
        assert log.priority == p.DEFAULT_PRIORITY > priority  # best effort stays below
        etag = slow_ecb.etags[name_to_uid("brake")]
        assert slow_ecb.granted == {(etag, pub.stats()["txnode"]): priority}
        with pytest.raises(ConfigError, match="declared"):
            pub.set_priority("brake", 0x90)


async def test_admission_refuses_a_stream_that_would_miss_and_names_it(
    bus: str, slow_ecb: CanEcb
) -> None:
    async with Node(can=bus, node_id=1) as a, Node(can=bus, node_id=2) as b:
        # alone, 'steer' waits at worst for one blocking frame: 2.56 ms <= 3 ms
        await a.declare("steer", period_ms=3, deadline_ms=3)
        # whichever of the two goes second would wait for two frames: 3.84 ms > 3 ms
        with pytest.raises(Unschedulable, match="would miss its deadline") as refused:
            await b.declare("throttle", period_ms=3, deadline_ms=3)
        assert f"0x{name_to_uid('throttle'):016x}" in str(refused.value)
        assert slow_ecb.stats()["refused"] == 1 and len(slow_ecb.declared) == 1
        # the refused channel still works, best effort
        s = await a.subscribe("throttle")
        await b.publish("throttle", b"\x07")
        assert (await s.get_msg(timeout=5)).priority == p.DEFAULT_PRIORITY
        # a stream that fits beside 'steer' is still admitted
        assert await b.declare("gear", period_ms=100, deadline_ms=50, size_bytes=1) > RT_FIRST


async def test_a_tighter_stream_moves_an_admitted_one(bus: str, slow_ecb: CanEcb) -> None:
    async with (
        Node(can=bus, node_id=1) as a,
        Node(can=bus, node_id=2) as b,
        Node(can=bus, node_id=3) as watcher,
    ):
        s = await watcher.subscribe("odometry")
        assert await a.declare("odometry", period_ms=20, deadline_ms=20) == RT_FIRST
        # 'estop' needs the top priority: below 'odometry' it would wait 3 frames (3.84 ms)
        assert await b.declare("estop", period_ms=50, deadline_ms=3) == RT_FIRST
        # the CAN-ECB tells node a its new priority (a's link may hear it a moment after b's)
        await eventually(lambda: a._states[name_to_uid("odometry")].priority == RT_FIRST + 1)
        await a.publish("odometry", b"\x00")
        assert (await s.get_msg(timeout=5)).priority == RT_FIRST + 1


async def test_declarations_survive_a_broker_restart(bus: str, tmp_path: Path) -> None:
    db = tmp_path / "ecb.db"
    async with running_ecb(bus, db, bitrate=SLOW) as first, Node(can=bus, node_id=1) as node:
        priority = await node.declare("brake", period_ms=10, deadline_ms=5, size_bytes=1)
        granted = dict(first.granted)
        first.close()
        async with running_ecb(bus, db, bitrate=SLOW) as second:  # Hello: declared again
            await eventually(lambda: second.granted == granted)
        assert list(granted.values()) == [priority]


async def test_bad_declarations_are_config_errors(bus: str, slow_ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as node:
        with pytest.raises(ConfigError, match="size_bytes"):
            await node.declare("x", period_ms=10, deadline_ms=10, size_bytes=70_000)
        with pytest.raises(ConfigError, match="period and deadline"):
            await node.declare("x", period_ms=0.01, deadline_ms=10)
        with pytest.raises(ConfigError, match="period and deadline"):
            await node.declare("x", period_ms=10_000, deadline_ms=10)
        assert slow_ecb.declared == {}
