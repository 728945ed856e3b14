"""The gateway between a virtual CAN bus and Zenoh, in one process, through a real router."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from ups import ConfigError, Node, name_to_uid
from ups.gateway import Gateway

from .conftest import eventually


@contextlib.asynccontextmanager
async def gateway(bus: str, endpoint: str, db: Path) -> AsyncIterator[Gateway]:
    async with Gateway(bus, zenoh=endpoint, db=db, node_id=0x6A7E, recovery=0.1) as gw:
        face: Any = gw.ip.face if gw.ip else None
        face.linger = 0.3  # seconds: quick, for the test
        yield gw


def forwarding(gw: Gateway, channel: str, to: str) -> bool:
    uid = name_to_uid(channel)
    return uid in (gw._to_ip_sinks if to == "zenoh" else gw._to_can_sinks)


async def test_can_to_zenoh_only_while_someone_subscribes(
    bus: str,
    zenoh_router: str,
    tmp_path: Path,
) -> None:
    async with (
        gateway(bus, zenoh_router, tmp_path / "gw.db") as gw,
        Node(can=bus, node_id=0xC1) as cpub,
        Node(zenoh=zenoh_router, node_id=0x71) as znode,
    ):
        cpub.set_priority("speed", 0x30)
        await cpub.publish("speed", b"\x00")
        assert not forwarding(gw, "speed", "zenoh") and gw.stats()["to_zenoh"] == 0
        sub = await znode.subscribe("speed")
        await eventually(lambda: forwarding(gw, "speed", "zenoh"))
        await cpub.publish("speed", b"\x01")
        msg = await sub.get_msg(timeout=5)
        assert (msg.data, msg.priority, msg.source) == (b"\x01", 0x30, 0x6A7E)
        await znode.unsubscribe(sub)
        await eventually(lambda: not forwarding(gw, "speed", "zenoh"))  # after the linger
        sent = gw.stats()["to_zenoh"]
        await cpub.publish("speed", b"\x02")
        assert gw.stats()["to_zenoh"] == sent


async def test_a_new_can_publishers_first_event_reaches_zenoh(
    bus: str,
    zenoh_router: str,
    tmp_path: Path,
) -> None:
    async with (
        gateway(bus, zenoh_router, tmp_path / "gw.db"),
        Node(can=bus, node_id=0xCA) as cpub,
        Node(zenoh=zenoh_router, node_id=0x7A) as znode,
    ):
        sub = await znode.subscribe("first")
        await cpub.publish("first", b"\x01")  # its very first event on a fresh channel
        assert (await sub.get_msg(timeout=5)).data == b"\x01"


async def test_zenoh_to_can_for_can_subscribers_never_back(
    bus: str,
    zenoh_router: str,
    tmp_path: Path,
) -> None:
    async with (
        gateway(bus, zenoh_router, tmp_path / "gw.db") as gw,
        Node(can=bus, node_id=0xC2) as cnode,
        Node(zenoh=zenoh_router, node_id=0x72) as zpub,
        Node(zenoh=zenoh_router, node_id=0x73) as zwatch,
    ):
        csub = await cnode.subscribe("cmd")
        watch = await zwatch.subscribe("cmd")
        await eventually(lambda: forwarding(gw, "cmd", "can"))
        zpub.set_priority("cmd", 0x40)
        for i in range(3):
            await zpub.publish("cmd", bytes([i]))
        got = [await csub.get_msg(timeout=5) for _ in range(3)]
        assert [(m.data, m.priority) for m in got] == [(bytes([i]), 0x40) for i in range(3)]
        # the Zenoh watcher hears each event once, from its publisher: never again from the
        # gateway, whose CAN copy of it does not go back to Zenoh
        heard = [await watch.get_msg(timeout=5) for _ in range(3)]
        assert {m.source for m in heard} == {0x72}
        with pytest.raises(TimeoutError):
            await watch.get_msg(timeout=0.5)
        assert gw.stats()["to_zenoh"] == 0 and gw.stats()["to_can"] == 3
        await cnode.unsubscribe(csub)
        await eventually(lambda: not forwarding(gw, "cmd", "can"))


def test_a_gateway_joins_one_ip_network() -> None:
    with pytest.raises(ConfigError, match="one IP network"):
        Gateway("virtual:x", "127.0.0.1:1", zenoh="tcp/127.0.0.1:1")
    with pytest.raises(ConfigError, match="one IP network"):
        Gateway("virtual:x")
