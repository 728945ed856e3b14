"""Pattern subscriptions in one process, on every network that knows names: a real TCP-ECB
(with and without an ACL), a real Zenoh router, and a virtual CAN bus with its CAN-ECB and a
channel catalog. A channel that is named later joins; a literal name is never a pattern."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from ups import AccessDenied, Channel, ConfigError, Message, Node, Subscription, name_to_uid
from ups import _tcpwire as w
from ups._catalog import Catalog
from ups._patterns import MAX_MATCHES
from ups.broker._acl import Acl
from ups.broker.tcp_ecb import TcpEcb

from .conftest import eventually
from .test_tcp_node import addr, running_tcp_ecb, tcp_node
from .test_tls import certs, tls

CATALOG = Path(__file__).resolve().parent.parent / "examples" / "robots.toml"


async def received(sub: Subscription, publisher: Node, channel: str, data: bytes) -> Message:
    """Publish ``data`` on ``channel`` until ``sub`` has it: a channel named just now joins once
    the subscriber has heard of it and subscribed, and what was published before is gone."""
    for _ in range(200):
        await publisher.publish(channel, data)
        with contextlib.suppress(TimeoutError):
            while (msg := await sub.get_msg(timeout=0.1)).channel.name != channel:
                pass
            return msg
    raise AssertionError(f"{channel} never reached the subscription: {sub!r}")


def names(sub: Subscription) -> set[str | None]:
    return {c.name for c in sub.channels}


@pytest.fixture
async def tcp_ecb() -> AsyncIterator[TcpEcb]:
    async with running_tcp_ecb() as ecb:
        yield ecb


async def test_tcp_a_pattern_gets_the_channels_named_now_and_later(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "a") as a, tcp_node(tcp_ecb, "b") as b:
        await b.advertise("robot/speed")  # named before the subscription
        await b.advertise("other/x")
        sub = await a.subscribe("robot/*")
        assert sub.patterns == ("robot/*",) and names(sub) == {"robot/speed"}
        msg = await received(sub, b, "robot/speed", b"\x32")
        assert msg.channel == Channel.named("robot/speed") and msg.source == b.node_id
        later = await received(sub, b, "robot/distance", b"\xc8")  # named after it
        assert later.channel.name == "robot/distance" and later.data == b"\xc8"
        await b.publish("other/x", b"\x01")
        assert names(sub) == {"robot/speed", "robot/distance"}
        assert tcp_ecb.stats()["watches"] == 1
        await a.unsubscribe("robot/*")
        await eventually(lambda: tcp_ecb.stats()["watches"] == 0)


async def test_a_name_that_holds_a_star_is_a_channel_only_when_asked_so(tcp_ecb: TcpEcb) -> None:
    literal = Channel.named("robot/*")
    async with tcp_node(tcp_ecb, "a") as a, tcp_node(tcp_ecb, "b") as b:
        sub = await a.subscribe(literal)
        assert sub.patterns == () and sub.channels == (literal,)
        await b.advertise(literal)
        await b.publish(literal, b"\x07")
        assert (await sub.get_msg(timeout=10)).channel == literal
        with pytest.raises(ConfigError, match="is a pattern"):
            await b.publish("robot/*", b"\x07")  # never a silent literal
        escaped = await a.subscribe("robot/[*]")  # the pattern that matches it alone
        assert escaped.channels == (literal,)


async def test_tcp_a_node_watches_at_most_64_patterns(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "a") as a:
        for i in range(64):
            await a.subscribe(f"p{i}/*")
        with pytest.raises(AccessDenied, match="at most 64 patterns") as refused:
            await a.subscribe("p64/*")
        assert refused.value.right == "watch"
        assert tcp_ecb.stats()["watch_limited"] == 1 and tcp_ecb.stats()["watches"] == 64


async def _watch_answer(ecb: TcpEcb, pattern: str) -> list[w.Names]:
    """Watch ``pattern`` from a node written by hand, and read the TCP-ECB's answer: its Names
    frames, up to the one marked done (10 s at most)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", ecb.port)
    writer.write(w.encode(w.Hello(0xA7, "raw", "127.0.0.1", 1)) + w.encode(w.Watch(pattern)))
    decoder = w.Decoder(max_frame=w.MAX_BODY)
    answer: list[w.Names] = []
    try:
        async with asyncio.timeout(10):
            while not answer or not answer[-1].done:
                data = await reader.read(1 << 16)
                assert data, f"the TCP-ECB closed the link after {_sizes(answer)}"
                answer += [f for f in decoder.feed(data) if isinstance(f, w.Names)]
    except TimeoutError:
        raise AssertionError(f"no final Names frame in 10 s, after {_sizes(answer)}") from None
    finally:
        writer.close()
    return answer


def _sizes(answer: list[w.Names]) -> list[tuple[int, bool]]:
    """Each Names frame as (channels, done)."""
    return [(len(frame.channels), frame.done) for frame in answer]


@pytest.mark.parametrize("count", [255, 256, 257, 512])
async def test_tcp_a_watch_is_answered_to_its_final_frame_whatever_the_count(
    tcp_ecb: TcpEcb, count: int
) -> None:
    """The answer to a Watch is Names frames of ``NAMES_PER_FRAME`` (256) channels, the last
    one done: also when the channels fill whole frames (mutation audit, issue 41: a Watch of
    exactly 256·k channels never got its final frame, and the node waited out its timeout)."""
    names_now = [f"w/{i:03}" for i in range(count)]
    async with tcp_node(tcp_ecb, "b") as b, tcp_node(tcp_ecb, "a") as a:
        for name in names_now:
            await b.advertise(name)
        answer = await _watch_answer(tcp_ecb, "w/*")
        whole, rest = divmod(count, w.NAMES_PER_FRAME)  # whole frames, then the rest if any
        sizes = [w.NAMES_PER_FRAME] * whole + ([rest] if rest else [])
        assert _sizes(answer) == [(n, i == len(sizes) - 1) for i, n in enumerate(sizes)]
        assert sorted(name for f in answer for _, name in f.channels) == names_now
        sub = await a.subscribe("w/*")  # a real node's watch: answered, every channel joined
        assert len(sub.channels) == count
        assert not a.face._watches._pending  # type: ignore[attr-defined]


@pytest.mark.parametrize("extra", [0, 1])
async def test_tcp_a_pattern_joins_at_most_max_matches_channels(
    tcp_ecb: TcpEcb, extra: int
) -> None:
    """A glob joins ``MAX_MATCHES`` channels (4096) and no more: exactly that many named, all
    join and nothing is counted; one more, and that one is left out and counted, once
    (mutation audit, issue 41: the bound was off by one unseen)."""
    count = MAX_MATCHES + extra
    async with tcp_node(tcp_ecb, "b") as b, tcp_node(tcp_ecb, "a") as a:
        for i in range(count):
            await b.advertise(f"m/{i:04}")
        sub = await a.subscribe("m/*")
        assert len(sub.channels) == MAX_MATCHES
        assert a.stats()["pattern_limited"] == extra


async def test_tcp_with_an_acl_a_pattern_names_only_what_the_identity_may_have(
    tmp_path: Path,
) -> None:
    certs(tmp_path, "ca", str(tmp_path))
    for name in ("broker", "alice", "bob"):
        certs(tmp_path, "issue", str(tmp_path), name)
    acl = Acl.parse('[identity.alice]\nsubscribe = ["robot/speed"]\n'
                    '[identity.bob]\npublish = ["robot/*"]\n')  # fmt: skip
    async with running_tcp_ecb(tls=tls(tmp_path, "broker"), acl=acl) as ecb:
        alice = Node(broker=addr(ecb), name="alice", tls=tls(tmp_path, "alice"))
        bob = Node(broker=addr(ecb), name="bob", tls=tls(tmp_path, "bob"))
        async with alice, bob:
            await bob.advertise("robot/speed")
            await bob.advertise("robot/brake")
            sub = await alice.subscribe("robot/*")
            assert names(sub) == {"robot/speed"}  # robot/brake is not named to alice
            assert (await received(sub, bob, "robot/speed", b"\x01")).data == b"\x01"
            await bob.advertise("robot/distance")
            await bob.publish("robot/speed", b"\x02")
            assert (await sub.get_msg(timeout=10)).data == b"\x02"
            assert names(sub) == {"robot/speed"} and alice.stats()["pattern_refused"] == 0


async def test_zenoh_a_pattern_gets_every_event_of_a_channel_from_its_first(
    zenoh_router: str,
) -> None:
    async with Node(zenoh=zenoh_router, name="a") as a, Node(zenoh=zenoh_router, name="b") as b:
        sub = await a.subscribe("robot/*")
        assert names(sub) == set()  # on Zenoh a channel is named by its events
        await b.advertise("robot/speed")
        face: Any = b.face
        await eventually(lambda: face.subscribed_elsewhere(name_to_uid("robot/speed")))
        for i in range(50):
            await b.publish("robot/speed", bytes([i]))
            await b.publish("other/x", bytes([i]))
        got = [await sub.get_msg(timeout=10) for _ in range(50)]
        assert [m.data[0] for m in got] == list(range(50))  # once each, in order, none lost
        assert {m.channel.name for m in got} == {"robot/speed"} and names(sub) == {"robot/speed"}
        assert a.stats()["lost"] == 0 and a.stats()["restarts"] == 0
        forged = f"ups/{name_to_uid('robot/speed') ^ 1:016x}/robot/speed"  # not its UID's name
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([zenoh_router]))
        plain = zenoh.open(conf)
        try:
            plain.put(forged, b"\xff")
            await b.publish("robot/speed", b"\x99")
            assert (await sub.get_msg(timeout=10)).data == b"\x99"  # the forged one is not
        finally:
            plain.close()  # type: ignore[no-untyped-call]
        await eventually(lambda: a.stats()["foreign"] >= 1)


async def test_can_a_pattern_takes_its_names_from_the_catalog(bus: str, ecb: Any) -> None:
    async with (
        Node(can=bus, name="a", catalog=CATALOG) as a,
        Node(can=bus, name="b") as b,
    ):
        sub = await a.subscribe("robot/*")
        catalogued = {s.name for s in Catalog.load(CATALOG) if (s.name or "").startswith("robot/")}
        assert names(sub) == catalogued and "robot/brake" in catalogued
        await b.publish("robot/brake", b"\x01")
        msg = await sub.get_msg(timeout=10)
        assert msg.channel.name == "robot/brake" and msg.data == b"\x01"
        with pytest.raises(ConfigError, match="names come only from a channel catalog"):
            await b.subscribe("robot/*")  # no catalog: refused, never a literal


async def _raw_publisher(node: Node, *frames: bytes) -> asyncio.StreamWriter:
    """A publisher's link to ``node``, written by hand: Hello, then ``frames``."""
    host, port = node.face.address
    _, writer = await asyncio.open_connection(host, port)
    writer.write(w.encode(w.Hello(0xFEED, "raw", "127.0.0.1", 1)) + b"".join(frames))
    await writer.drain()
    return writer


async def test_tcp_a_start_that_comes_before_the_names_waits_for_them(tcp_ecb: TcpEcb) -> None:
    """A publisher's Start (and event) of a channel the node does not subscribe to yet, while it
    watches a pattern, waits for the TCP-ECB's Names; one never named goes on after 1 s,
    counted as unsubscribed. Nothing is delivered twice, nothing out of order."""
    uid, other = name_to_uid("fleet/early"), name_to_uid("other/never")
    async with tcp_node(tcp_ecb, "a") as a, tcp_node(tcp_ecb, "b") as b:
        sub = await a.subscribe("fleet/*")
        writer = await _raw_publisher(
            a, w.encode(w.Start(uid, 1)), w.encode_event(uid, b"\x01", 0x80, 1),
            w.encode_event(uid, b"\x02", 0x80, 2),
        )  # fmt: skip
        await b.advertise("fleet/early")  # the ECB names it to a's pattern now
        got = [await sub.get_msg(timeout=5) for _ in range(2)]
        assert [m.data for m in got] == [b"\x01", b"\x02"] and got[0].channel.name == "fleet/early"
        writer.write(w.encode(w.Start(other, 1)) + w.encode_event(other, b"\x09", 0x80, 1)
                     + w.encode_event(uid, b"\x03", 0x80, 3))  # fmt: skip
        await writer.drain()
        msg = await sub.get_msg(timeout=5)  # after the second the name of other/never is owed
        assert msg.data == b"\x03" and a.stats()["unsubscribed"] == 1
        assert a.stats()["lost"] == 0
        writer.close()


async def test_tcp_a_pattern_subscriber_back_at_another_address_is_reached_there(
    tcp_ecb: TcpEcb,
) -> None:
    """The same node id says Hello again from a new process (another listening port) before
    the old one left: its publishers are told its new address for its pattern's channels too."""
    async with tcp_node(tcp_ecb, "p") as p:
        await p.advertise("fleet/a")
        old = tcp_node(tcp_ecb, "w", node_id=0xBEEF)
        await old.start()
        await old.subscribe("fleet/*")  # the ECB lists it, at its old address, for fleet/a
        try:
            async with tcp_node(tcp_ecb, "w", node_id=0xBEEF) as new:
                sub = await new.subscribe("fleet/*")
                msg = await received(sub, p, "fleet/a", b"\x07")
                assert msg.channel.name == "fleet/a"
        finally:
            await old.close()
