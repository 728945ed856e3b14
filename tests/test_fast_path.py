"""The lean per-event path: callback subscriptions, publish_nowait, and large TCP events written
without copies, on real loopback sockets and virtual CAN buses."""

from __future__ import annotations

import hashlib
import logging
import os

import pytest

from ups import ConfigError, Message, Node
from ups import _tcpwire as w
from ups._tcplink import QUEUE_BYTES
from ups.broker.can_ecb import CanEcb
from ups.broker.tcp_ecb import TcpEcb

from .conftest import eventually
from .test_tcp_node import (  # noqa: F401  (tcp_ecb: the fixture)
    registered_at,
    stalled_subscriber,
    tcp_ecb,
    tcp_node,
)


async def test_a_callback_gets_every_event_in_order_and_survives_its_own_errors(
    tcp_ecb: TcpEcb,  # noqa: F811
    caplog: pytest.LogCaptureFixture,
) -> None:
    got: list[bytes] = []

    def on_event(msg: Message) -> None:
        got.append(msg.data)
        if msg.data[0] % 3 == 0:
            raise RuntimeError(f"callback trouble at {msg.data[0]}")

    async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "sub") as node:
        sub = await node.subscribe("cb", callback=on_event)
        await pub.advertise("cb")
        with caplog.at_level(logging.ERROR, logger="ups"):
            for i in range(1, 31):
                pub.publish_nowait("cb", bytes([i]))
            await eventually(lambda: len(got) == 30)
        assert got == [bytes([i]) for i in range(1, 31)]
        assert sub.errors == 10 and node.stats()["callback_errors"] == 10
        assert node.stats()["lost"] == 0
        assert "callback trouble at 3" in caplog.text  # logged, once a second at most
        assert "callback trouble at 6" not in caplog.text
        with pytest.raises(ConfigError, match="callback"):
            await sub.get_msg(timeout=0.1)


async def test_publish_nowait_needs_a_binding_that_carries_the_event(
    tcp_ecb: TcpEcb,  # noqa: F811
) -> None:
    async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "sub") as node:
        sub = await node.subscribe("nw")
        with pytest.raises(ConfigError, match="advertise"):
            pub.publish_nowait("nw", b"too early")
        await pub.advertise("nw")
        pub.publish_nowait("nw", b"now")
        pub.publish_nowait(sub.channels[0].uid, b"by uid")  # the same channel, named otherwise
        assert (await sub.get_msg(timeout=5)).data == b"now"
        assert (await sub.get_msg(timeout=5)).data == b"by uid"
        with pytest.raises(ConfigError, match="max_size"):
            pub.publish_nowait("nw", bytes(w.MAX_DATA + 1))


async def test_publish_nowait_and_callbacks_on_can(bus: str, ecb: CanEcb) -> None:
    got: list[Message] = []
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as node:
        await node.subscribe("c", callback=got.append)
        await pub.advertise("c")
        pub.publish_nowait("c", b"12345678")
        with pytest.raises(ConfigError, match="max_size=9"):
            pub.publish_nowait("c", b"123456789")  # a larger size class needs the CAN-ECB
        await pub.advertise("c", max_size=9)
        pub.publish_nowait("c", b"123456789")
        await eventually(lambda: len(got) == 2)
        assert [m.data for m in got] == [b"12345678", b"123456789"]


async def test_mebibyte_events_arrive_whole_while_a_stalled_peer_holds_a_bounded_queue(
    tcp_ecb: TcpEcb,  # noqa: F811
) -> None:
    """Large events are queued as header and data, never copied in bulk: the subscriber that
    reads gets every one intact; the one that does not read costs a queue bounded in bytes,
    and every event dropped from it is counted."""
    with stalled_subscriber() as stalled:
        host, port = stalled.getsockname()
        async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "fast") as fast:
            sub = await fast.subscribe("big", maxlen=4)
            uid = sub.channels[0].uid
            async with registered_at(tcp_ecb, 0x52, (host, port), uid):
                await pub.advertise("big")
                targets = pub.face._outbox._targets  # type: ignore[attr-defined]
                await eventually(lambda: len(targets.get(uid, ())) == 2)
                peers = {p.node_id: p for p in targets[uid]}
                stalled_link = peers[0x52].link
                count = 100
                for i in range(count):
                    data = os.urandom(w.MAX_DATA - i)  # 1 MiB and just below
                    await pub.publish("big", data)
                    msg = await sub.get_msg(timeout=10)
                    assert hashlib.sha256(msg.data).digest() == hashlib.sha256(data).digest()
                    assert stalled_link._out_bytes <= QUEUE_BYTES + w.MAX_DATA + w.EVENT_HEADER
                assert fast.stats()["lost"] == 0
                dropped = pub.stats()["peer_dropped"]
                assert 0 < dropped < count  # what the stalled queue could hold was kept
                assert stalled_link.dropped == dropped
                assert stalled_link.queued + dropped <= count
