"""The gateway in one process: virtual CAN buses, a TCP-ECB and TCP nodes on loopback."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import can
import pytest

from ups import ConfigError, Node, name_to_uid
from ups import _canproto as p
from ups._canlink import CanLink
from ups._tcpface import query_status
from ups.broker.can_ecb import CanEcb
from ups.broker.tcp_ecb import TcpEcb
from ups.gateway import Gateway

from .conftest import eventually
from .test_tcp_node import running_tcp_ecb


@pytest.fixture
async def tcp_ecb() -> AsyncIterator[TcpEcb]:
    async with running_tcp_ecb() as ecb:
        yield ecb


def addr(ecb: TcpEcb) -> str:
    return f"127.0.0.1:{ecb.port}"


@contextlib.asynccontextmanager
async def gateway(bus: str, ecb: TcpEcb, db: Path, **options: Any) -> AsyncIterator[Gateway]:
    options.setdefault("node_id", 0x6A7E)
    options.setdefault("recovery", 0.1)  # the hosted CAN-ECB's: nodes join after it
    async with Gateway(bus, addr(ecb), db=db, **options) as gw:
        yield gw


def can_node(bus: str, node_id: int) -> Node:
    return Node(can=bus, node_id=node_id, name=f"can-{node_id:x}")


def tcp_node(ecb: TcpEcb, node_id: int) -> Node:
    return Node(broker=addr(ecb), node_id=node_id, name=f"tcp-{node_id:x}")


def forwarding(gw: Gateway, channel: str, to: str) -> bool:
    uid = name_to_uid(channel)
    return uid in (gw._to_ip_sinks if to == "tcp" else gw._to_can_sinks)


async def test_can_publisher_to_tcp_subscriber_keeps_the_priority(
    bus: str, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    async with (
        gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw,
        can_node(bus, 0xC1) as cpub,
        tcp_node(tcp_ecb, 0x71) as tsub_node,
    ):
        sub = await tsub_node.subscribe("speed")
        cpub.set_priority("speed", 0x30)
        await cpub.publish("speed", b"\x00")  # binds; the gateway starts forwarding after it
        await eventually(lambda: forwarding(gw, "speed", "tcp"))
        await cpub.publish("speed", b"\x01\x02")
        msg = await sub.get_msg(timeout=5)
        while msg.data == b"\x00":
            msg = await sub.get_msg(timeout=5)
        assert (msg.data, msg.priority, msg.channel.name) == (b"\x01\x02", 0x30, "speed")
        assert gw.stats()["to_tcp"] >= 1
        await tsub_node.close()  # the only TCP subscriber goes: the gateway stops listening on CAN
        await eventually(lambda: not forwarding(gw, "speed", "tcp"))
        await eventually(lambda: gw._ecb.subscribers[name_to_uid("speed")] == set())  # type: ignore[union-attr]
        sent = gw.stats()["to_tcp"]
        await cpub.publish("speed", b"\x03")
        assert gw.stats()["to_tcp"] == sent


async def test_a_new_can_publishers_first_event_reaches_tcp(
    bus: str, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    """The hosted CAN-ECB answers a new publisher's binding only once the gateway forwards."""
    async with (
        gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw,
        can_node(bus, 0xCA) as cpub,
        tcp_node(tcp_ecb, 0x7A) as tsub_node,
    ):
        sub = await tsub_node.subscribe("first")
        await cpub.publish("first", b"\x01")  # its very first event on a fresh channel
        assert (await sub.get_msg(timeout=5)).data == b"\x01"
        assert forwarding(gw, "first", "tcp")


async def test_tcp_publisher_to_can_subscriber_keeps_the_priority(
    bus: str, raw_bus: can.BusABC, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    async with (
        gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw,
        can_node(bus, 0xC2) as csub_node,
        tcp_node(tcp_ecb, 0x72) as tpub,
    ):
        sub = await csub_node.subscribe("cmd")
        await eventually(lambda: forwarding(gw, "cmd", "can"))
        tpub.set_priority("cmd", 0x40)
        await tpub.publish("cmd", b"\x09")
        msg = await sub.get_msg(timeout=5)
        assert (msg.data, msg.priority) == (b"\x09", 0x40)
        etag = csub_node.face.bindings.bound[name_to_uid("cmd")]  # type: ignore[attr-defined]
        txnode = gw.can.stats()["txnode"]  # type: ignore[union-attr]
        assert msg.source == txnode  # on CAN, the gateway is the sender
        frames = []
        while (frame := raw_bus.recv(0.2)) is not None:
            frames.append(frame.arbitration_id)
        assert p.make_id(0x40, txnode, etag) in frames


async def test_nothing_reaches_the_bus_without_a_can_subscriber(
    bus: str, raw_bus: can.BusABC, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    async with (
        gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw,
        can_node(bus, 0xC3) as csub_node,
        tcp_node(tcp_ecb, 0x73) as tpub,
    ):
        sub = await csub_node.subscribe("cmd")
        await eventually(lambda: forwarding(gw, "cmd", "can"))
        await sub.close()  # the last CAN subscriber leaves: the gateway withdraws on TCP
        await eventually(lambda: not forwarding(gw, "cmd", "can"))
        await eventually(lambda: name_to_uid("cmd") not in tcp_ecb._subscribers)
        for _ in range(5):
            await tpub.publish("cmd", b"\x01")
            await tpub.publish("lonely", b"\x02")
        assert tpub.stats()["sent"] == 0  # nobody on TCP subscribes: nothing even leaves
        events = []
        while (frame := raw_bus.recv(0.3)) is not None:
            if not p.is_management(frame.arbitration_id):
                events.append(frame)
        assert events == []
        assert gw.stats()["to_can"] == 0


async def test_no_event_is_reflected_into_the_network_it_came_from(
    bus: str, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    """Channel x has publishers and subscribers on both sides: each event arrives once."""
    async with (
        gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw,
        can_node(bus, 0xC4) as cpub,
        can_node(bus, 0xC5) as csub_node,
        tcp_node(tcp_ecb, 0x74) as tpub,
        tcp_node(tcp_ecb, 0x75) as tsub_node,
    ):
        csub = await csub_node.subscribe("x")
        tsub = await tsub_node.subscribe("x")
        await cpub.publish("x", b"\x00")
        await tpub.publish("x", b"\x00")
        await eventually(lambda: forwarding(gw, "x", "tcp") and forwarding(gw, "x", "can"))
        await eventually(lambda: tpub.stats()["peers"] == 2)  # tsub and the gateway
        for sub in (csub, tsub):  # forget the set-up events
            while sub.pending or await _more(sub):
                await sub.get_msg(timeout=0)
        before = dict(gw.stats())
        await cpub.publish("x", b"C")
        await tpub.publish("x", b"T")
        got_can = sorted([(await csub.get_msg(timeout=5)).data for _ in range(2)])
        got_tcp = sorted([(await tsub.get_msg(timeout=5)).data for _ in range(2)])
        assert got_can == got_tcp == [b"C", b"T"]
        assert not await _more(csub) and not await _more(tsub)  # no second copies
        after = gw.stats()
        assert after["to_can"] - before["to_can"] == 1
        assert after["to_tcp"] - before["to_tcp"] == 1


async def _more(sub: Any) -> bool:
    try:
        msg = await sub.get_msg(timeout=0.3)
    except TimeoutError:
        return False
    sub._queue.appendleft(msg)
    return True


async def test_wan_of_cans(bus: str, tcp_ecb: TcpEcb, tmp_path: Path) -> None:
    bus_b = bus + "-b"
    async with (
        gateway(bus, tcp_ecb, tmp_path / "a.db", node_id=0x6A) as gw_a,
        gateway(bus_b, tcp_ecb, tmp_path / "b.db", node_id=0x6B) as gw_b,
        can_node(bus, 0xA1) as on_a,
        can_node(bus_b, 0xB1) as on_b,
        tcp_node(tcp_ecb, 0x76) as host,
    ):
        a_hears = await on_a.subscribe("from-b")
        b_hears = await on_b.subscribe("from-a")
        host_hears = await host.subscribe("from-a", "from-b")
        await on_a.publish("from-a", b"\x00")
        await on_b.publish("from-b", b"\x00")
        await eventually(
            lambda: forwarding(gw_a, "from-a", "tcp") and forwarding(gw_b, "from-b", "tcp")
        )
        await eventually(
            lambda: forwarding(gw_a, "from-b", "can") and forwarding(gw_b, "from-a", "can")
        )
        await eventually(lambda: gw_a._ip_face().subscribed_elsewhere(name_to_uid("from-a")))
        await on_a.publish("from-a", b"\xaa")
        await on_b.publish("from-b", b"\xbb")
        assert await _next_not_zero(b_hears) == b"\xaa"
        assert await _next_not_zero(a_hears) == b"\xbb"
        assert {await _next_not_zero(host_hears), await _next_not_zero(host_hears)} == {
            b"\xaa",
            b"\xbb",
        }


async def _next_not_zero(sub: Any) -> bytes:
    while (data := (await sub.get_msg(timeout=5)).data) == b"\x00":
        pass
    return bytes(data)


async def test_a_flood_towards_can_is_paced_and_its_drops_counted(
    bus: str, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    async with (
        gateway(bus, tcp_ecb, tmp_path / "gw.db", bitrate=20_000, can_queue=8) as gw,
        can_node(bus, 0xC6) as csub_node,
        tcp_node(tcp_ecb, 0x77) as tpub,
    ):
        sub = await csub_node.subscribe("cmd", maxlen=10_000)
        await eventually(lambda: forwarding(gw, "cmd", "can"))
        await tpub.publish("cmd", b"\x00")
        await eventually(lambda: gw.stats()["to_can"] == 1)
        await tpub.publish("cmd", bytes(70_000))  # too big for any event on CAN
        for i in range(500):
            await tpub.publish("cmd", i.to_bytes(2, "big"))
        await eventually(lambda: gw.ip.stats()["received"] == 502)  # type: ignore[union-attr]
        stats = gw.stats()
        assert stats["too_large_for_can"] == 1
        assert stats["can_dropped"] > 400  # 20 kbit/s carries ~200 frames a second
        await eventually(lambda: gw.stats()["can_queued"] == 0)
        stats = gw.stats()
        assert stats["to_can"] + stats["can_dropped"] == 501  # every event is accounted for
        await eventually(lambda: sub.pending == stats["to_can"])
        got = []
        while sub.pending:
            got.append(await sub.get_msg(timeout=0))
        assert len(got) == stats["to_can"]
        assert got[-1].data == (499).to_bytes(2, "big")  # drop_oldest: the newest got through


async def test_a_restarted_gateway_keeps_bindings_and_forwards_again(
    bus: str, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    db = tmp_path / "gw.db"
    first = Gateway(bus, addr(tcp_ecb), db=db, node_id=0x6A7E)
    await first.start()
    try:
        async with can_node(bus, 0xC7) as cpub, tcp_node(tcp_ecb, 0x78) as tsub_node:
            sub = await tsub_node.subscribe("speed")
            await cpub.publish("speed", b"\x00")
            await eventually(lambda: forwarding(first, "speed", "tcp"))
            txnode = cpub.stats()["txnode"]
            etag = cpub.face.bindings.bound[name_to_uid("speed")]  # type: ignore[attr-defined]
            await first.close()
            async with gateway(bus, tcp_ecb, db, recovery=2.0) as second:
                # it relearns the bus during its recovery window (2 s) and then forwards
                await eventually(lambda: forwarding(second, "speed", "tcp"), timeout=15)
                await cpub.publish("speed", b"\x01")
                assert await _next_not_zero(sub) == b"\x01"
                assert cpub.stats()["txnode"] == txnode
                assert cpub.face.bindings.bound[name_to_uid("speed")] == etag  # type: ignore[attr-defined]
    finally:
        await first.close()


async def test_gateway_with_an_external_can_ecb(bus: str, tcp_ecb: TcpEcb, tmp_path: Path) -> None:
    link = CanLink.open(bus)
    ecb = CanEcb(link, tmp_path / "ecb.db", recovery=0.1)
    await ecb.start()
    try:
        async with (
            gateway(bus, tcp_ecb, tmp_path / "unused.db", host_can_ecb=False) as gw,
            can_node(bus, 0xC8) as csub_node,
            tcp_node(tcp_ecb, 0x79) as tpub,
        ):
            sub = await csub_node.subscribe("cmd")
            await eventually(lambda: forwarding(gw, "cmd", "can"))
            await tpub.publish("cmd", b"\x05")
            assert (await sub.get_msg(timeout=5)).data == b"\x05"
            assert not (tmp_path / "unused.db").exists()
    finally:
        ecb.close()
        link.close()


async def test_gateway_status_is_readable(bus: str, tcp_ecb: TcpEcb, tmp_path: Path) -> None:
    async with gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw, can_node(bus, 0xC9) as csub:
        await csub.subscribe("cmd")
        await eventually(lambda: forwarding(gw, "cmd", "can"))
        host, port = gw._ip_face().address  # type: ignore[misc]
        info = (await query_status(f"{host}:{port}"))["gateway"]
        assert info["channels_to_can"] == (f"0x{name_to_uid('cmd'):016x}",)
        assert info["forwarding_to_can"] == 1
        assert info["txnode"] == gw.can.stats()["txnode"]  # type: ignore[union-attr]
        assert info["can_ecb"]["txnodes"] == 2


async def test_bad_gateway_options(tcp_ecb: TcpEcb) -> None:
    with pytest.raises(ConfigError, match="can_queue"):
        Gateway("virtual:x", addr(tcp_ecb), can_queue=0)
    with pytest.raises(ConfigError, match="bitrate"):
        Gateway("virtual:x", addr(tcp_ecb), bitrate=0)


async def test_a_forged_bind_never_stops_tcp_to_can(
    bus: str, raw_bus: can.BusABC, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    """A stray Bind that moves the forwarded channel's etag: the gateway's CAN node binds it
    again and forwarding goes on; nothing is sent on an etag it no longer relies on."""
    async with (
        gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw,
        can_node(bus, 0xC3) as csub_node,
        tcp_node(tcp_ecb, 0x73) as tpub,
    ):
        sub = await csub_node.subscribe("cmd")
        await eventually(lambda: forwarding(gw, "cmd", "can"))
        await tpub.publish("cmd", b"\x01")
        assert (await sub.get_msg(timeout=5)).data == b"\x01"
        etag = csub_node.face.bindings.bound[name_to_uid("cmd")]  # type: ignore[attr-defined]
        can_id, data = p.encode(p.Bind(etag, name_to_uid("not/cmd")))
        raw_bus.send(can.Message(arbitration_id=can_id, data=data))
        await eventually(lambda: gw.can.stats()["rebinds"] >= 1)  # type: ignore[union-attr]
        for i in range(2, 40):  # TCP->CAN goes on through the re-binding
            await tpub.publish("cmd", bytes([i]))
            await asyncio.sleep(0.005)
        await eventually(lambda: gw.can.stats()["bindings"] >= 1)  # type: ignore[union-attr]
        await tpub.publish("cmd", b"\xff")
        got = []
        while (msg := await sub.get_msg(timeout=5)).data != b"\xff":
            got.append(msg.data)
        assert all(len(d) == 1 and 2 <= d[0] < 40 for d in got)
        stats = gw.stats()
        assert stats["pacer_errors"] == 0 and stats["reconcile_errors"] == 0
        assert gw._ecb is not None and gw._ecb.stats()["conflicts"] >= 1


async def test_the_gateways_own_binding_passes_its_bind_gate(
    bus: str, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    """While the gateway brings a channel's forwarding in line, a CAN publisher's binding of
    it waits (the CAN-ECB's bind gate), but not the gateway's own: the reconcile awaits that
    one, and waited out the gate's timeout, a second for every channel forwarded to CAN."""
    async with gateway(bus, tcp_ecb, tmp_path / "gw.db") as gw:
        uid, own = name_to_uid("cmd"), gw.stats()["txnode"]
        gw._backlog.running.add(uid)  # as while reconciling it
        mine = asyncio.ensure_future(gw._until_settled(uid, own))
        other = asyncio.ensure_future(gw._until_settled(uid, own + 1))
        await asyncio.sleep(0)
        assert mine.done() and not other.done()
        other.cancel()
        gw._backlog.running.discard(uid)


async def test_close_ends_a_task_that_swallowed_its_cancel(
    bus: str, tcp_ecb: TcpEcb, tmp_path: Path
) -> None:
    """Python 3.11's wait_for can swallow a cancel that meets its result: the reconcile loop
    then waited for work forever, close() with it, and ``ups demo`` hung on Ctrl-C. close()
    cancels again until the task ends."""
    gw = Gateway(bus, addr(tcp_ecb), db=tmp_path / "gw.db", node_id=0x6A7E)
    await gw.start()

    async def stubborn() -> None:
        with contextlib.suppress(asyncio.CancelledError):  # swallowed once, as wait_for may
            await asyncio.Event().wait()
        await asyncio.Event().wait()

    task = asyncio.create_task(stubborn())
    gw._tasks.append(task)
    await asyncio.sleep(0)  # it runs, and waits
    closing = asyncio.create_task(gw.close())
    await asyncio.wait({closing}, timeout=30)  # a bound for a hang, not a measurement
    assert closing.done() and task.cancelled()
    closing.cancel()  # if it hung: the test's own end
