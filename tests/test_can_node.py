"""Nodes and the CAN-ECB on python-can virtual buses, in one process."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path

import can
import pytest

from ups import (
    BrokerUnavailable,
    Closed,
    ConfigError,
    Exhausted,
    Node,
    PayloadTooLarge,
    name_to_uid,
)
from ups import _canproto as p
from ups.broker._store import Store
from ups.broker.can_ecb import CanEcb

from .conftest import eventually, running_ecb


def etag_of(node: Node, channel: str) -> int:
    return node.face.bindings.bound[name_to_uid(channel)]  # type: ignore[attr-defined,no-any-return]


async def test_simultaneous_joiners_get_distinct_txnodes(bus: str, ecb: CanEcb) -> None:
    ids = [0xFFFF_0000_0000_0001, 0x1234, 0x8000_0000_0000_0000, 0x1235, 0x0FED_CBA9_8765_4321]
    nodes = [Node(can=bus, node_id=i) for i in ids]
    try:
        await asyncio.gather(*(n.start() for n in nodes))
        txnodes = {n.node_id: n.stats()["txnode"] for n in nodes}
        assert sorted(txnodes.values()) == list(range(len(ids)))
        assert ecb.txnodes == txnodes
    finally:
        for n in nodes:
            await n.close()


async def test_restarted_node_keeps_its_txnode(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=7) as a, Node(can=bus, node_id=9) as b:
        first = a.stats()["txnode"], b.stats()["txnode"]
    async with Node(can=bus, node_id=9) as b, Node(can=bus, node_id=7) as a:
        assert (a.stats()["txnode"], b.stats()["txnode"]) == first


async def test_default_node_ids_differ_between_live_nodes_and_survive_restart(
    bus: str, ecb: CanEcb
) -> None:
    async with Node(can=bus, name="twin") as a, Node(can=bus, name="twin") as b:
        assert a.node_id != b.node_id
        first = a.node_id
    async with Node(can=bus, name="twin") as a:
        assert a.node_id == first


async def test_node_waits_for_a_late_ecb(bus: str, tmp_path: Path, raw_bus: can.BusABC) -> None:
    node = Node(can=bus, node_id=0x42, join_timeout=10)
    joining = asyncio.create_task(node.start())
    # the node is asking: its first offer is on the bus before any ECB exists
    frame = await asyncio.to_thread(raw_bus.recv, 5.0)
    assert frame is not None and isinstance(p.decode(frame.arbitration_id, frame.data), p.Knock)
    try:
        async with running_ecb(bus, tmp_path / "late.db", recovery=0.1):
            await asyncio.wait_for(joining, 10)
            assert node.stats()["txnode"] == 0
    finally:
        await node.close()


async def test_join_without_ecb_times_out_clearly(bus: str) -> None:
    node = Node(can=bus, node_id=1, join_timeout=0.3)
    with pytest.raises(BrokerUnavailable, match="no CAN-ECB gave this node a TxNode"):
        await node.start()
    await node.close()


async def test_txnodes_run_out_with_a_clear_error(bus: str, tmp_path: Path) -> None:
    Store(tmp_path / "full.db").close()  # creates the tables
    with sqlite3.connect(tmp_path / "full.db") as db:
        rows = [(f"{0xAAAA_0000 + t:016x}", t) for t in range(p.TXNODE_COUNT)]
        db.executemany("INSERT INTO txnodes VALUES (?, ?)", rows)
    async with running_ecb(bus, tmp_path / "full.db", recovery=0.1) as full:
        async with Node(can=bus, node_id=0xAAAA_0005) as known:  # known nodes still join
            assert known.stats()["txnode"] == 5
        with pytest.raises(Exhausted, match="127 TxNodes"):
            await Node(can=bus, node_id=0xBEEF, join_timeout=5).start()
        assert full.stats()["refused"] == 1


async def test_etags_run_out_with_a_clear_error(bus: str, tmp_path: Path) -> None:
    Store(tmp_path / "full.db").close()  # creates the tables
    with sqlite3.connect(tmp_path / "full.db") as db:
        rows = [(f"{e:016x}", e) for e in range(p.FIRST_ETAG, p.LAST_ETAG + 1)]
        db.executemany("INSERT INTO etags VALUES (?, ?)", rows)
    async with (
        running_ecb(bus, tmp_path / "full.db", recovery=0.1),
        Node(can=bus, node_id=1) as node,
    ):
        with pytest.raises(Exhausted, match="no etag left"):
            await node.subscribe("one/too/many")
        await node.subscribe(p.FIRST_ETAG + 3)  # a bound channel still works


async def test_publish_reaches_local_and_remote_subscribers_only(bus: str, ecb: CanEcb) -> None:
    async with (
        Node(can=bus, node_id=1) as pub,
        Node(can=bus, node_id=2) as sub,
        Node(can=bus, node_id=3) as other,
    ):
        remote = await sub.subscribe("speed")
        local = await pub.subscribe("speed")
        elsewhere = await other.subscribe("heading")
        await pub.publish("speed", b"\x01\x02")
        got_remote = await remote.get_msg(timeout=5)
        got_local = await local.get_msg(timeout=5)
        assert got_remote.data == got_local.data == b"\x01\x02"
        assert got_remote.channel.name == "speed" and got_remote.source == pub.stats()["txnode"]
        assert got_local.source is None  # delivered in-process, not from the bus
        assert got_remote.priority == p.DEFAULT_PRIORITY
        # a barrier: once this arrives, the speed event has passed 'other' (the bus is FIFO)
        await sub.publish("heading", b"\xff")
        assert (await elsewhere.get_msg(timeout=5)).data == b"\xff"
        assert elsewhere.pending == 0
        assert etag_of(pub, "speed") == etag_of(sub, "speed")
        assert pub.stats()["own_echo"] == 0 and pub.stats()["sent"] == 1


async def test_priority_is_on_the_wire(bus: str, ecb: CanEcb, raw_bus: can.BusABC) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as sub:
        s = await sub.subscribe("brake")
        pub.set_priority("brake", 0x10)
        await pub.publish("brake", b"\x01")
        msg = await s.get_msg(timeout=5)
        assert msg.priority == 0x10
    frames = []
    while (f := raw_bus.recv(0)) is not None:
        frames.append(f)
    events = [f for f in frames if not p.is_management(f.arbitration_id)]
    assert len(events) == 1
    etag = ecb.etags[name_to_uid("brake")]
    assert events[0].arbitration_id == p.make_id(0x10, pub.stats()["txnode"], etag)


async def test_unsubscribe_stops_delivery(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as sub:
        speed = await sub.subscribe("speed")
        barrier = await sub.subscribe("barrier")
        await pub.publish("speed", b"\x01")
        assert (await speed.get_msg(timeout=5)).data == b"\x01"
        await sub.unsubscribe("speed")
        await pub.publish("speed", b"\x02")
        await pub.publish("barrier", b"\x00")
        await barrier.get_msg(timeout=5)
        with pytest.raises(Closed):
            await speed.get_msg(timeout=0)
        await eventually(lambda: not ecb.subscribers[name_to_uid("speed")])
        assert sub.stats()["delivered"] == 2  # speed once, barrier once


async def test_ecb_restart_keeps_every_binding(bus: str, tmp_path: Path) -> None:
    db = tmp_path / "ecb.db"
    async with running_ecb(bus, db) as first, Node(can=bus, node_id=0x11) as a:
        for name in ("a", "b", "c"):
            await a.subscribe(name)
        before = first.etags
        txnode = a.stats()["txnode"]
        first.close()  # the broker dies; the node keeps running
        async with running_ecb(bus, db) as second:  # its Hello makes the node announce again
            await eventually(lambda: len([u for u, s in second.subscribers.items() if s]) == 3)
            assert second.etags == before
            assert second.txnodes == {0x11: txnode}
            async with Node(can=bus, node_id=0x22) as b:
                await b.publish("b", b"x")
                assert etag_of(b, "b") == before[name_to_uid("b")]


async def test_claim_recovers_a_lost_ecb_database(bus: str, tmp_path: Path) -> None:
    async with running_ecb(bus, tmp_path / "one.db") as first, Node(can=bus, node_id=0x99) as node:
        txnode = node.stats()["txnode"]
        first.close()
        async with running_ecb(bus, tmp_path / "two.db") as fresh:  # the tables are gone
            await eventually(lambda: fresh.txnodes == {0x99: txnode})


async def test_foreign_frames_are_skipped_and_counted(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    async with (
        Node(can=bus, node_id=1) as pub,
        Node(can=bus, node_id=2, filter_limit=0) as sub,  # software filtering: sees every frame
    ):
        s = await sub.subscribe("speed")
        await pub.publish("other", b"")  # bound, but sub is not subscribed
        raw_bus.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
        raw_bus.send(can.Message(arbitration_id=0x123, is_remote_frame=True, is_extended_id=False))
        raw_bus.send(can.Message(arbitration_id=p.make_id(0x80, 0x50, 0x3ABC), data=b"\x01"))
        raw_bus.send(can.Message(arbitration_id=p.make_id(0x00, 0x7F, 0x3E00), data=b""))
        await pub.publish("speed", b"\x07")  # the barrier
        assert (await s.get_msg(timeout=5)).data == b"\x07"
        stats = sub.stats()
        assert stats["foreign"] == 2  # the 11-bit data frame and the remote frame
        assert stats["unknown"] == 1  # a 29-bit frame on an etag nobody bound
        assert stats["malformed"] == 1  # in the management space, but no UPS frame
        assert stats["filtered"] == 1  # the 'other' event
        assert stats["delivered"] == 1
        # the CAN-ECB reads the bus on its own thread: it counts the same frames, in its time
        await eventually(lambda: (ecb.stats()["foreign"], ecb.stats()["malformed"]) == (2, 1))


async def test_acceptance_filters_keep_unwanted_frames_away(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as sub:
        s = await sub.subscribe("speed")
        raw_bus.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
        await pub.publish("other", b"")
        await pub.publish("speed", b"\x07")
        assert (await s.get_msg(timeout=5)).data == b"\x07"
        stats = sub.stats()
        assert stats["foreign"] == stats["filtered"] == 0  # dropped below the node


async def test_many_channels_filter_in_software(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2, filter_limit=2) as sub:
        subs = [await sub.subscribe(f"ch{i}") for i in range(4)]
        await pub.publish("not-subscribed", b"\x00")
        for i in range(4):
            await pub.publish(f"ch{i}", bytes([i]))
        for i, s in enumerate(subs):
            assert (await s.get_msg(timeout=5)).data == bytes([i])
        assert sub.stats()["filtered"] == 1


async def test_bad_input_gives_clear_errors(bus: str, ecb: CanEcb) -> None:
    with pytest.raises(ConfigError, match="INTERFACE:CHANNEL"):
        await Node(can="vcan0", node_id=1).start()
    with pytest.raises(ConfigError, match="cannot open CAN bus"):
        await Node(can="no_such_interface:x", node_id=1).start()
    with pytest.raises(ConfigError):
        Node(can=bus, node_id=1 << 64)
    async with Node(can=bus, node_id=1) as node:
        with pytest.raises(PayloadTooLarge, match="65536 bytes"):
            await node.publish("speed", bytes(65536))
        await node.publish("speed", bytes(8))
        with pytest.raises(ConfigError):
            node.set_priority("speed", 256)
        with pytest.raises(ConfigError):
            await node.subscribe()
        with pytest.raises(ConfigError):
            await node.subscribe("x", maxlen=0)
        with pytest.raises(ConfigError):
            await node.subscribe("x", overflow="block")  # type: ignore[arg-type]
        s = await node.subscribe("quiet")
        with pytest.raises(TimeoutError):
            await s.get_msg(timeout=0.01)
    with pytest.raises(Closed):
        await node.publish("speed", b"")
    with pytest.raises(Closed):
        await node.get_msg(timeout=0)


async def test_queue_overflow_policies_count_drops(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as node:
        oldest = await node.subscribe("x", maxlen=2)
        newest = await node.subscribe("x", maxlen=2, overflow="drop_newest")
        for i in range(5):
            await node.publish("x", bytes([i]))
        assert [(await oldest.get_msg(0)).data for _ in range(2)] == [b"\x03", b"\x04"]
        assert [(await newest.get_msg(0)).data for _ in range(2)] == [b"\x00", b"\x01"]
        assert oldest.dropped == newest.dropped == 3
        assert node.stats()["dropped"] == 6


async def test_iteration_and_node_get_msg(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as node:
        a = await node.subscribe("a")
        b = await node.subscribe("b")
        await node.publish("b", b"1")
        await node.publish("a", b"2")
        await node.publish("b", b"3")
        got = [await node.get_msg(timeout=1) for _ in range(3)]
        assert [m.data for m in got] == [b"1", b"2", b"3"]  # oldest first, across subscriptions

        async def consume() -> list[bytes]:
            return [m.data async for m in a]

        reader = asyncio.create_task(consume())
        await node.publish("a", b"x")
        await node.publish("a", b"y")
        await eventually(lambda: a.pending == 0)
        await a.close()
        assert await asyncio.wait_for(reader, 5) == [b"x", b"y"]
        assert b.pending == 0


async def test_a_false_claim_leaves_the_holder_alone(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    async with Node(can=bus, node_id=0x11) as holder:
        await holder.subscribe("a")
        txnode = holder.stats()["txnode"]
        # another node id claims the holder's TxNode (say, a node configured from a stale copy)
        can_id, data = p.encode(p.Request(p.CLAIM, txnode, 0x999))
        raw_bus.send(can.Message(arbitration_id=can_id, data=data))
        # claims answer a Hello; outside the recovery window one is ignored and counted
        await eventually(lambda: ecb.stats()["conflicts"] == 1)
        assert 0x999 not in ecb.txnodes and ecb.txnodes[0x11] == txnode
        assert ecb.subscribers[name_to_uid("a")] == {txnode}  # the holder keeps its channels
