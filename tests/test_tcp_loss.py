"""TCP/IP: every event a publisher accepts is delivered or counted as lost, at both ends.
In one process, on real loopback sockets."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator

import pytest

from ups import Node
from ups._tcpface import query_status
from ups.broker.tcp_ecb import TcpEcb

from .conftest import eventually
from .procs import start_tcp_broker
from .test_tcp_node import running_tcp_ecb, tcp_node

N = 1100  # more than a peer queue holds (1024)


@pytest.fixture
async def tcp_ecb() -> AsyncIterator[TcpEcb]:
    async with running_tcp_ecb() as ecb:
        yield ecb


async def _drain(sub_node: Node, sub: object, until: int) -> list[int]:
    got = []
    while len(got) + sub_node.stats()["lost"] < until:
        msg = await sub.get_msg(timeout=5)  # type: ignore[attr-defined]
        got.append(int.from_bytes(msg.data, "big"))
    return got


async def test_a_tight_publishing_loop_loses_nothing_uncounted(tcp_ecb: TcpEcb) -> None:
    """A newcomer's first script: subscribe, then publish flat out before any link is up."""
    async with tcp_node(tcp_ecb, "sub") as sub_node, tcp_node(tcp_ecb, "pub") as pub:
        sub = await sub_node.subscribe("tight", maxlen=N)
        for i in range(N):  # never yields: the link to the subscriber is not even up yet
            await pub.publish("tight", i.to_bytes(2, "big"))
        got = await _drain(sub_node, sub, N)
        lost_at_sub = sub_node.stats()["lost"]
        await eventually(lambda: pub.stats()["peer_dropped"] == lost_at_sub)
        assert len(got) + lost_at_sub == N  # delivered, or counted at both ends
        assert got == sorted(got) and got[-1] == N - 1  # in order; the newest kept
        assert sub_node.stats()["malformed"] == 0 and sub.dropped == 0


async def test_backpressure_delivers_everything(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "sub") as sub_node, tcp_node(tcp_ecb, "pub") as pub:
        sub = await sub_node.subscribe("waited", maxlen=N)
        for i in range(N):
            await pub.publish("waited", i.to_bytes(2, "big"), wait=True)
        got = await _drain(sub_node, sub, N)
        assert got == list(range(N))
        assert sub_node.stats()["lost"] == 0 and pub.stats()["peer_dropped"] == 0


@pytest.mark.pure  # keeps the subscriber away by patching its face
async def test_a_subscriber_off_the_lists_counts_what_it_missed() -> None:
    """Taken for dead by the TCP-ECB (here: its ECB link cut, and liveness passed), the
    subscriber misses events; when it is back, the publisher's Start tells it how many."""
    async with (
        running_tcp_ecb(liveness=1.0) as ecb,
        tcp_node(ecb, "sub") as sub_node,
        tcp_node(ecb, "pub") as pub,
    ):
        sub = await sub_node.subscribe("gap")
        await pub.publish("gap", b"\x00")
        assert (await sub.get_msg(timeout=5)).data == b"\x00"
        face = sub_node.face
        face._ecb.abort("test: cut")  # type: ignore[attr-defined]
        face._reconnect_ecb = _never  # type: ignore[attr-defined]  # stays away
        await eventually(lambda: not pub.face.subscribed_elsewhere(sub.channels[0].uid), 10)
        for i in range(1, 11):  # nobody subscribes, as far as the publisher knows
            await pub.publish("gap", bytes([i]))
        await face._connect_ecb()  # type: ignore[attr-defined]  # back, and registered
        await eventually(lambda: pub.face.subscribed_elsewhere(sub.channels[0].uid), 10)
        await pub.publish("gap", b"\x0b")
        assert (await sub.get_msg(timeout=5)).data == b"\x0b"
        assert sub_node.stats()["lost"] == 10


async def _never() -> None:
    await asyncio.Event().wait()


async def test_a_consumer_draining_a_deep_queue_is_not_taken_for_dead() -> None:
    """get_msg gives the loop a turn now and then: heartbeats go on while a slow consumer
    works through a deep queue for longer than the TCP-ECB's liveness timeout (the TCP-ECB
    runs as a process, so that it is not starved along with the consumer)."""
    broker, address = start_tcp_broker("--liveness", "1", "--recovery", "0")
    with broker:
        async with (
            Node(broker=address, node_id=0xD1, name="sub") as sub_node,
            Node(broker=address, node_id=0xD2, name="pub") as pub,
        ):
            sub = await sub_node.subscribe("deep", maxlen=100_000)
            for i in range(60_000):
                await pub.publish("deep", b"x", wait=True)
                if i % 1000 == 0:
                    await asyncio.sleep(0)
            await eventually(lambda: sub.pending >= 60_000, 20)
            start = time.monotonic()
            while sub.pending:
                await sub.get_msg()
                end = time.perf_counter() + 30e-6  # a little work per event
                while time.perf_counter() < end:
                    pass
            assert time.monotonic() - start > 1.5  # longer than the liveness timeout
            await asyncio.sleep(0.6)  # a heartbeat's time: an evicted node would notice now
            status = await query_status(address)
            assert status["stats"]["left"] == 0, status["stats"]
            assert sub_node.stats()["reconnects"] == 0
