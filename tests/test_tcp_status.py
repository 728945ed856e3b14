"""The TCP-ECB's Status costs what it lists: it counts its channels as the tables change (no
union of them all per Status) and lists the first that registered."""

from __future__ import annotations

import pytest

from ups import Node, name_to_uid
from ups._tcpface import query_status
from ups.broker import _tcpstatus

from .conftest import eventually
from .test_tcp_node import running_tcp_ecb


def _hex(name: str) -> str:
    return f"0x{name_to_uid(name):016x}"


async def test_the_channel_count_and_the_listing_follow_the_tables(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(_tcpstatus, "STATUS_LIST", 2)
    async with running_tcp_ecb() as ecb:
        address = f"127.0.0.1:{ecb.port}"
        a = Node(broker=address, node_id=0xA1, join_timeout=5)
        b = Node(broker=address, node_id=0xB2, join_timeout=5)
        async with a, b:
            sub_x = await a.subscribe("st/x")
            await a.subscribe("st/y")
            await b.advertise("st/y")  # subscribed by a too: still one channel
            await b.advertise("st/z")  # only published on
            assert ecb.stats()["channels"] == 3
            status = await query_status(address)
            # the first two that registered, subscribed ones first, listed sorted
            assert [c["uid"] for c in status["channels"]] == sorted([_hex("st/x"), _hex("st/y")])
            assert status["listed"] == {"nodes": 2, "channels": 2, "at_most": 2}

            await a.unsubscribe(sub_x)
            await eventually(lambda: ecb.stats()["channels"] == 2)
            status = await query_status(address)
            assert [c["uid"] for c in status["channels"]] == sorted([_hex("st/y"), _hex("st/z")])
        await eventually(lambda: ecb.stats()["channels"] == 0 and ecb.stats()["nodes"] == 0)
