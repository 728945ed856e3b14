"""libups (c/), the C node, beside the real CAN-ECB and Python nodes on a virtual bus.

The compiled library runs through ``ups._cnode`` (ctypes), driven every millisecond as a
microcontroller's main loop would drive it; the CAN-ECB and the Python nodes are the product's.
"""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from ups import Node, name_to_uid
from ups import _canproto as p
from ups._cnode import ERRORS, NOTE_FILTERS, CNode

from .cnode_helpers import CanEcb, c_nodes, now_ms
from .conftest import eventually, running_ecb

SPEED, CMD = name_to_uid("robot/speed"), name_to_uid("robot/cmd")


async def test_joins_binds_and_exchanges_events_with_python_nodes(bus: str, ecb: CanEcb) -> None:
    async with c_nodes(bus, 0xC0DE) as c, Node(can=bus, node_id=0x5B) as py:
        await c.joined()
        node = c.nodes[0]
        assert ecb.txnodes[0xC0DE] == node.txnode
        speed = node.subscribe(SPEED, now_ms())
        cmd = node.advertise(CMD, 8, now_ms())
        etag = await c.bound(node, speed)
        assert etag == ecb.etags[SPEED]
        assert node.filters() == [(0x7F << 14, 0x7F << 14), (etag, 0x3FFF)]
        await c.bound(node, cmd)
        sub = await py.subscribe("robot/cmd")
        await py.publish("robot/speed", b"\x01\x02")
        await c.until(lambda: c.events(node, speed) == [b"\x01\x02"])
        assert node.publish(cmd, b"\xaa" * 8) == 0
        msg = await sub.get_msg(timeout=5)
        assert msg.data == b"\xaa" * 8 and msg.source == node.txnode and msg.priority == 0x80
        assert node.publish(cmd, b"\x00" * 9) == -4  # TOO_LARGE: 8 bytes on this channel


async def test_minimal_build_interoperates(bus: str, ecb: CanEcb) -> None:
    async with c_nodes(bus, 0x1, variant="min") as c, Node(can=bus, node_id=2) as py:
        node = c.nodes[0]
        assert node.config["channels"] == 8 and node.config["max_event"] == 8
        speed = node.subscribe(SPEED, now_ms())
        await c.joined()
        await c.bound(node, speed)
        await py.publish("robot/speed", b"hi")
        await c.until(lambda: c.events(node, speed) == [b"hi"])


async def test_two_c_nodes_and_python_nodes_join_together(bus: str, ecb: CanEcb) -> None:
    ids = [0x1234, 0x1235, 0xFFFF_0000_0000_0001]
    async with c_nodes(bus, *ids) as c, Node(can=bus, node_id=0x1236) as py:
        await c.joined()
        txnodes = {n.node_id: n.txnode for n in c.nodes} | {py.node_id: py.stats()["txnode"]}
        assert len(set(txnodes.values())) == 4
        assert ecb.txnodes == txnodes


@pytest.mark.parametrize("keep_db", [True, False], ids=["with-db", "lost-db"])
async def test_ecb_restart_keeps_the_c_nodes_etags(bus: str, tmp_path: Path, keep_db: bool) -> None:
    async with (
        running_ecb(bus, tmp_path / "one.db", recovery=0.3) as first,
        c_nodes(bus, 0xC1) as c,
        Node(can=bus, node_id=0x77) as py,
    ):
        node = c.nodes[0]
        speed = node.subscribe(SPEED, now_ms())
        cmd = node.advertise(CMD, 8, now_ms())
        etags = await c.bound(node, speed), await c.bound(node, cmd)
        txnode = node.txnode
        first.close()
        db = tmp_path / ("one.db" if keep_db else "two.db")
        async with running_ecb(bus, db, recovery=0.3) as second:  # its Hello: announce
            await eventually(
                lambda: (
                    second.txnodes.get(0xC1) == txnode
                    and txnode in second.subscribers.get(SPEED, ())
                    and txnode in second.publishers.get(CMD, ())
                )
            )
            assert (second.etags[SPEED], second.etags[CMD]) == etags
            assert node.txnode == txnode
            assert (node.channel_etag(speed), node.channel_etag(cmd)) == etags
            await py.publish("robot/speed", b"after")
            await c.until(lambda: c.events(node, speed) == [b"after"])
        assert node.counters()["rebinds"] == 0


async def test_forged_binds_never_deliver_another_channel(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    other = name_to_uid("robot/other")
    async with c_nodes(bus, 0xC2) as c, Node(can=bus, node_id=0x78) as py:
        node = c.nodes[0]
        speed = node.subscribe(SPEED, now_ms())
        etag = await c.bound(node, speed)
        await py.advertise("robot/other")
        other_etag = ecb.etags[other]
        for forged in (p.Bind(other_etag, SPEED), p.Bind(etag, other)):
            can_id, data = p.encode(forged)
            raw_bus.send(can.Message(arbitration_id=can_id, data=data))
            await py.publish("robot/other", b"wrong")  # on other_etag, or on etag once moved
            await c.until(lambda: node.counters()["rebinds"] > 0)
            await c.bound(node, speed)  # the CAN-ECB's correction, settled
            assert node.channel_etag(speed) == etag
            await py.publish("robot/other", b"wrong")
            await py.publish("robot/speed", b"right")
            await c.until(lambda: c.events(node, speed)[-1:] == [b"right"])
        assert set(c.events(node, speed)) == {b"right"}
        assert node.notes() & NOTE_FILTERS


async def test_limit_and_txnodes_full_are_reported(
    bus: str, tmp_path: Path, raw_bus: can.BusABC
) -> None:
    async with (
        running_ecb(bus, tmp_path / "l.db", recovery=0.1, max_channels=1),
        c_nodes(bus, 0xC3) as c,
    ):
        node = c.nodes[0]
        first = node.subscribe(SPEED, now_ms())
        await c.bound(node, first)
        second = node.subscribe(CMD, now_ms())
        await c.until(lambda: node.channel_state(second) < 0)
        assert ERRORS[node.channel_state(second)] == "LIMIT"
    # no CAN-ECB: a forged TxNodesFull ends the join, once it stood the refusal wait (3 s)
    async with c_nodes(bus, 0xC4) as c:
        can_id, data = p.encode(p.TxNodesFull(0xC4))
        raw_bus.send(can.Message(arbitration_id=can_id, data=data))
        await c.until(lambda: c.nodes[0].join_state < 0)
        assert ERRORS[c.nodes[0].join_state] == "TXNODES_FULL"


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
async def test_large_events_both_ways(bus: str, tmp_path: Path, fd: bool) -> None:
    spec = f"{bus},fd=True" if fd else bus
    async with (
        running_ecb(spec, tmp_path / "big.db", recovery=0.1),
        c_nodes(bus, 0xC5, fd=fd) as c,
        Node(can=spec, node_id=0x79) as py,
    ):
        node = c.nodes[0]
        big_in = node.subscribe(name_to_uid("big/in"), now_ms())
        big_out = node.advertise(name_to_uid("big/out"), 1000, now_ms())
        sub = await py.subscribe("big/out")
        await py.advertise("big/in", max_size=1024)
        await c.bound(node, big_in)
        assert node.channel_etag(big_in) >= 0x3400  # class 2: up to 1024 bytes
        event = bytes(range(256)) * 3
        await py.publish("big/in", event)
        await c.until(lambda: c.events(node, big_in) == [event])
        await c.bound(node, big_out)
        out = bytes(reversed(range(256))) * 3 + b"end"
        assert node.publish(big_out, out) == 0
        if not fd:  # 111 frames do not fit the TX queue: one transfer at a time
            assert node.publish(big_out, b"x" * 100) == -5  # BUSY
        msg = await sub.get_msg(timeout=5)
        assert msg.data == out
        assert node.counters()["large_lost"] == 0


async def test_declaration_is_granted_and_sets_the_priority(bus: str, ecb: CanEcb) -> None:
    async with c_nodes(bus, 0xC6) as c, Node(can=bus, node_id=0x7A) as py:
        node = c.nodes[0]
        cmd = node.advertise(CMD, 8, now_ms())
        await c.bound(node, cmd)
        assert node.declare(cmd, 2, 100, 50, 0, now_ms()) == 0  # 2 bytes every 10 ms, 5 ms
        await c.until(lambda: node.declaration_state(cmd) == 2)
        sub = await py.subscribe("robot/cmd")
        assert node.publish(cmd, b"\x01\x02") == 0
        msg = await sub.get_msg(timeout=5)
        assert msg.priority == 0x02


def test_c_constants_match_the_header() -> None:
    header = (Path(__file__).parent.parent / "c" / "ups.h").read_text()
    from ups import _cnode

    for value, name in ERRORS.items():
        assert f"#define UPS_ERR_{name} ({value})" in header
    for name in ("EXT", "FD", "BRS", "RTR", "ERR"):
        assert f"#define UPS_FRAME_{name} 0x{getattr(_cnode, 'FRAME_' + name):02x}u" in header
    assert CNode(1).config["mtu"] == 64


async def test_a_node_does_not_subscribe_to_events_larger_than_it_buffers(
    bus: str, ecb: CanEcb
) -> None:
    async with c_nodes(bus, 0xC7, variant="min") as c, Node(can=bus, node_id=0x7B) as py:
        await py.advertise("big/in", max_size=100)  # class 2: events up to 1024 bytes
        node = c.nodes[0]
        big = node.subscribe(name_to_uid("big/in"), now_ms())
        await c.until(lambda: node.channel_state(big) < 0)
        assert ERRORS[node.channel_state(big)] == "TOO_LARGE"
        assert node.filters() == [(0x7F << 14, 0x7F << 14)]
        await eventually(lambda: not ecb.subscribers.get(name_to_uid("big/in")))
        node.unsubscribe(big)  # the entry is free again
        assert node.channel_state(big) == 0
