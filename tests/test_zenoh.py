"""The Zenoh face in one process: UPS nodes and plain Zenoh sessions through a real Zenoh
router on loopback (Zenoh's own, as ``ups zenoh-router`` runs it)."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ups import BlockingNode, BrokerUnavailable, ConfigError, Node, PayloadTooLarge, name_to_uid
from ups import _zenohface as zf

from .conftest import PATIENT_DROP, eventually


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def config(mode: str, **endpoints: list[str]) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    for key, value in endpoints.items():
        conf.insert_json5(f"{key}/endpoints", json.dumps(value))
    return conf


@pytest.fixture(scope="module")
def router(zenoh_router: str) -> str:
    return zenoh_router


@pytest.fixture
def plain(router: str) -> Iterator[zenoh.Session]:
    """A plain Zenoh client session: no UPS code."""
    session = zenoh.open(config("client", connect=[router]))
    yield session
    session.close()  # type: ignore[no-untyped-call]


@pytest.fixture
async def pair(router: str) -> AsyncIterator[tuple[Node, Node]]:
    async with Node(zenoh=router, node_id=0xA1) as a, Node(zenoh=router, node_id=0xB2) as b:
        yield a, b


async def matched(node: Node, channel: str | int) -> None:
    """Wait until a subscriber elsewhere matches what ``node`` publishes on ``channel``."""
    await node.advertise(channel)
    uid = name_to_uid(channel) if isinstance(channel, str) else channel
    face: Any = node.face
    await eventually(lambda: face.subscribed_elsewhere(uid))


def attachment(priority: int, node_id: int, seq: int) -> bytes:
    return struct.pack(">BBQQ", 1, priority, node_id, seq)


async def test_events_reach_subscribers_with_source_and_priority(pair: tuple[Node, Node]) -> None:
    a, b = pair
    sub = await b.subscribe("robot/speed")
    await matched(a, "robot/speed")
    a.set_priority("robot/speed", 0x30)
    for i in range(5):
        await a.publish("robot/speed", bytes([i]))
    got = [await sub.get_msg(timeout=5) for _ in range(5)]
    assert [m.data for m in got] == [bytes([i]) for i in range(5)]
    assert {(m.source, m.priority, m.channel.name) for m in got} == {(0xA1, 0x30, "robot/speed")}
    assert b.stats()["received"] == 5 and b.stats()["lost"] == 0
    assert a.stats()["sent"] == 5


async def test_bound_means_bound_a_subscription_is_known_when_subscribe_returns(
    pair: tuple[Node, Node],
) -> None:
    """``subscribe`` returns once the router has the subscription, and ``advertise`` once
    the router told the publisher who subscribes: the first event is not lost."""
    a, b = pair
    for i in range(5):
        channel = f"first/{i}"
        sub = await b.subscribe(channel)
        await a.advertise(channel)
        face: Any = a.face
        assert face.subscribed_elsewhere(name_to_uid(channel))
        await a.publish(channel, b"first")
        assert (await sub.get_msg(timeout=5)).data == b"first"
    assert a.stats()["sync_timeouts"] == b.stats()["sync_timeouts"] == 0


async def test_a_named_publisher_reaches_a_uid_subscriber_and_back(pair: tuple[Node, Node]) -> None:
    a, b = pair
    uid = name_to_uid("arm/joint")
    by_uid = await b.subscribe(uid)
    by_name = await a.subscribe("arm/joint")
    await matched(a, "arm/joint")
    await matched(b, uid)
    await a.publish("arm/joint", b"named")
    await b.publish(uid, b"bare")
    # each hears the other's event from Zenoh and its own locally: each once, none twice
    for sub in (by_uid, by_name):
        assert sorted([(await sub.get_msg(timeout=5)).data for _ in range(2)]) == [
            b"bare",
            b"named",
        ]
    with pytest.raises(TimeoutError):
        await b.get_msg(timeout=0.3)


async def test_a_plain_zenoh_subscriber_reads_ups_events(
    pair: tuple[Node, Node], plain: zenoh.Session
) -> None:
    a, _ = pair
    by_name: list[tuple[str, bytes]] = []
    by_uid: list[bytes] = []
    s1 = plain.declare_subscriber(
        "ups/*/robot/odom", lambda s: by_name.append((str(s.key_expr), s.payload.to_bytes()))
    )
    s2 = plain.declare_subscriber(
        f"ups/{name_to_uid('robot/odom'):016x}/**", lambda s: by_uid.append(s.payload.to_bytes())
    )
    await matched(a, "robot/odom")
    await a.publish("robot/odom", b"\x01\x02")
    await eventually(lambda: len(by_name) == 1 and len(by_uid) == 1)
    key = f"ups/{name_to_uid('robot/odom'):016x}/robot/odom"
    assert by_name == [(key, b"\x01\x02")] and by_uid == [b"\x01\x02"]
    s1.undeclare()
    s2.undeclare()


async def test_a_plain_zenoh_publisher_reaches_ups_subscribers(
    pair: tuple[Node, Node], plain: zenoh.Session
) -> None:
    _, b = pair
    sub = await b.subscribe("cmd/vel")
    uid = name_to_uid("cmd/vel")
    publisher = plain.declare_publisher(f"ups/{uid:016x}", priority=zenoh.Priority.INTERACTIVE_HIGH)
    await eventually(lambda: publisher.matching_status.matching)
    publisher.put(b"go")
    msg = await sub.get_msg(timeout=5)
    assert (msg.data, msg.source) == (b"go", None)
    assert zf.to_zenoh_priority(msg.priority) == 2  # the band it came with
    assert b.stats()["foreign"] == 1 and b.stats()["lost"] == 0
    publisher.undeclare()


@settings(
    max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(numbers=st.lists(st.integers(0, 40), min_size=1, max_size=12))
def test_skipped_numbers_are_counted_as_lost_once(router: str, numbers: list[int]) -> None:
    """Whatever numbers a publisher's events carry, a subscriber counts every number skipped
    forward as one lost event, never a wrong one, and delivers every event it got."""

    async def run() -> None:
        session = await asyncio.to_thread(zenoh.open, config("client", connect=[router]))
        try:
            async with Node(zenoh=router, node_id=0xC3) as node:
                sub = await node.subscribe(0x5EC)
                publisher = session.declare_publisher("ups/00000000000005ec")
                await eventually(lambda: publisher.matching_status.matching)
                for seq in numbers:
                    publisher.put(bytes([seq]), attachment=attachment(0x90, 0x77, seq))
                got = [await sub.get_msg(timeout=5) for _ in numbers]
                assert [m.data[0] for m in got] == numbers
                assert {(m.source, m.priority) for m in got} == {(0x77, 0x90)}
                lost, expected = 0, None
                for seq in numbers:
                    if expected is not None and seq > expected:
                        lost += seq - expected
                    expected = seq + 1
                assert node.stats()["lost"] == lost
                publisher.undeclare()
        finally:
            session.close()  # type: ignore[no-untyped-call]

    asyncio.run(run())


async def test_unsubscribed_channels_are_not_delivered_and_matching_follows(
    pair: tuple[Node, Node],
) -> None:
    a, b = pair
    face: Any = a.face
    uid = name_to_uid("lidar/scan")
    await a.advertise("lidar/scan")
    assert not face.subscribed_elsewhere(uid)
    changes: list[int] = []
    face.on_targets = changes.append
    sub = await b.subscribe("lidar/scan")
    await eventually(lambda: face.subscribed_elsewhere(uid))
    await b.unsubscribe(sub)
    await eventually(lambda: not face.subscribed_elsewhere(uid))
    assert changes == [uid, uid]
    await a.publish("lidar/scan", b"x")
    with pytest.raises(TimeoutError):
        await b.get_msg(timeout=0.3)
    assert b.stats()["delivered"] == 0


async def test_async_for_and_a_full_queue_counted(pair: tuple[Node, Node]) -> None:
    a, b = pair
    sub = await b.subscribe("iter", maxlen=4, overflow="drop_oldest")
    await a.advertise("iter")
    for i in range(10):
        a.publish_nowait("iter", bytes([i]))
    await eventually(lambda: b.stats()["received"] == 10)
    got = []
    async for msg in sub:
        got.append(msg.data[0])
        if len(got) == 4:
            break
    assert got == [6, 7, 8, 9] and sub.dropped == 6 and b.stats()["dropped"] == 6


async def test_callback_subscriptions_and_publish_nowait(pair: tuple[Node, Node]) -> None:
    a, b = pair
    seen: list[bytes] = []
    await b.subscribe("tick", callback=lambda m: seen.append(m.data))
    await matched(a, "tick")
    for i in range(100):
        a.publish_nowait("tick", i.to_bytes(2, "big"))
    await eventually(lambda: len(seen) == 100)
    assert seen == [i.to_bytes(2, "big") for i in range(100)]


async def test_a_mebibyte_event_and_no_more(router: str, tmp_path: Path) -> None:
    # The publisher's Zenoh waits for room rather than drop at once (as the router does): a
    # mebibyte is 17 batches through a queue of 2, and on a busy machine the thread that
    # empties it can take longer than Zenoh's default 20-50 ms to get a core.
    patient = tmp_path / "patient.json5"
    drop = {"congestion_control": {"drop": PATIENT_DROP}}
    patient.write_text(json.dumps({"transport": {"link": {"tx": {"queue": drop}}}}))
    async with (
        Node(zenoh=router, node_id=0xA1, zenoh_config=patient) as a,
        Node(zenoh=router, node_id=0xB2) as b,
    ):
        sub = await b.subscribe("map")
        await matched(a, "map")
        big = bytes(range(256)) * 4096
        await a.publish("map", big)
        assert (await sub.get_msg(timeout=5)).data == big
        with pytest.raises(PayloadTooLarge):
            await a.publish("map", big + b"!")


async def test_overflowing_the_receive_queue_is_counted(
    router: str, plain: zenoh.Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Samples Zenoh hands over while the event loop is busy wait in a bounded queue; what
    does not fit is counted, and delivered plus counted is everything sent."""
    monkeypatch.setattr(zf, "RX_QUEUE", 10)
    async with Node(zenoh=router, node_id=0xD4) as node:
        sub = await node.subscribe(0xF10, maxlen=1000)
        publisher = plain.declare_publisher("ups/0000000000000f10")
        await eventually(lambda: publisher.matching_status.matching)
        face: Any = node.face
        for i in range(100):
            publisher.put(bytes([i]), attachment=attachment(0x80, 0x55, i))
        deadline = time.monotonic() + 10  # the loop is held here, as a busy consumer would
        while len(face._rx) + face.counters["rx_overflow"] < 100:
            assert time.monotonic() < deadline, "Zenoh did not hand the samples over"
            time.sleep(0.01)  # noqa: ASYNC251 (holding the loop is the point)
        await eventually(lambda: sub.pending == 10)
        assert node.stats()["rx_overflow"] == 90
        assert [(await sub.get_msg(timeout=0)).data[0] for _ in range(10)] == list(range(10))
        publisher.undeclare()


async def test_joining_nothing_fails_clearly_after_the_join_timeout() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(BrokerUnavailable, match="ups zenoh-router"):
        async with Node(zenoh=endpoint, join_timeout=0.3):
            pass


def test_bad_options_are_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="listen: not an option of zenoh nodes"):
        asyncio.run(Node(zenoh="tcp/127.0.0.1:1", listen="127.0.0.1:0").start())
    with pytest.raises(ConfigError, match="one network"):
        Node(zenoh="tcp/127.0.0.1:1", broker="127.0.0.1:1")
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(ConfigError, match="bad Zenoh config"):
        asyncio.run(Node(zenoh_config=bad).start())
    with pytest.raises(ConfigError, match="bad Zenoh endpoint"):
        asyncio.run(Node(zenoh="nonsense").start())


def test_blocking_node_on_zenoh(router: str) -> None:
    with BlockingNode(zenoh=router, node_id=0xE5) as a, BlockingNode(zenoh=router) as b:
        sub = b.subscribe("blocking/zenoh")
        deadline = time.monotonic() + 5
        a.publish("blocking/zenoh", b"1")  # binds; then wait for the match
        face: Any = a.node.face
        while not face.subscribed_elsewhere(name_to_uid("blocking/zenoh")):
            assert time.monotonic() < deadline
            time.sleep(0.01)
        a.publish("blocking/zenoh", b"2")
        first = sub.get_msg(timeout=5).data  # "1" too, if Zenoh knew the subscriber already
        assert first == b"2" or (first == b"1" and sub.get_msg(timeout=5).data == b"2")


def test_priorities_map_onto_zenoh_bands_and_back() -> None:
    bands = [zf.to_zenoh_priority(p) for p in range(256)]
    assert bands[0] == 1 and bands[255] == 7 and bands == sorted(bands)
    assert set(bands) == set(range(1, 8))
    for band in range(1, 8):  # an event without UPS numbers keeps its band
        assert zf.to_zenoh_priority(zf.from_zenoh_priority(band)) == band
    assert zf.channel_key(0x1, "a/b") == "ups/0000000000000001/a/b"
    for odd in ("a/*", "a//b", "/a", "@x", "a$b", "q?"):  # not usable in a key: the UID alone
        assert zf.channel_key(0x1, odd) == "ups/0000000000000001"
