"""Events larger than one frame on python-can virtual buses, classic and CAN FD, in one process.

Real nodes and a real CAN-ECB; a raw python-can bus on the side injects, drops and repeats
frames. Every event that arrives must be exactly one that was published; what is lost is
counted.
"""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import can
import pytest

from ups import ConfigError, Node, PayloadTooLarge, name_to_uid
from ups import _canproto as p
from ups import _cantransfer as t
from ups.broker.can_ecb import CanEcb

from .conftest import eventually, running_ecb

SIZES = [0, 1, 8, 9, 61, 62, 64, 255, 256, 257, 1024, 4096, 65535]


def etag_of(node: Node, channel: str) -> int:
    return node.face.bindings.bound[name_to_uid(channel)]  # type: ignore[attr-defined,no-any-return]


@pytest.fixture(params=["classic", "fd"])
def fd_bus(request: pytest.FixtureRequest, bus: str) -> str:
    return bus + (",fd=True" if request.param == "fd" else "")


async def test_events_of_every_size_arrive_whole(fd_bus: str, tmp_path: Path) -> None:
    async with (
        running_ecb(fd_bus, tmp_path / "ecb.db", recovery=0.1),
        Node(can=fd_bus, node_id=1) as pub,
        Node(can=fd_bus, node_id=2) as sub_node,
    ):
        subs = {n: await sub_node.subscribe(f"size/{n}") for n in SIZES}
        events = {n: os.urandom(n) for n in SIZES}
        for n in SIZES:
            await pub.advertise(f"size/{n}", max_size=n)
            await pub.publish(f"size/{n}", events[n])
        for n in SIZES:
            msg = await subs[n].get_msg(timeout=5)
            assert msg.data == events[n], n
            assert msg.source == pub.stats()["txnode"]
            expected_class = t.class_for(n)
            assert t.size_class(etag_of(sub_node, f"size/{n}")) == expected_class
        assert sub_node.stats()["large_lost"] == 0


async def test_a_growing_channel_moves_its_subscribers_along(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as sub_node:
        sub = await sub_node.subscribe("grow")
        await pub.publish("grow", b"small")
        assert (await sub.get_msg(timeout=5)).data == b"small"
        small = etag_of(sub_node, "grow")
        big = os.urandom(300)
        await pub.publish("grow", big)  # moves the channel to class 2, then sends
        assert (await sub.get_msg(timeout=5)).data == big
        assert etag_of(sub_node, "grow") != small
        assert t.size_class(etag_of(sub_node, "grow")) == 2
        assert ecb.etags[name_to_uid("grow")] == etag_of(pub, "grow")
        await pub.publish("grow", b"tiny again")  # a large channel carries small events too
        assert (await sub.get_msg(timeout=5)).data == b"tiny again"
        assert ecb.counters["moved"] == 1
        assert sub_node.stats()["moves"] == 1 and sub_node.stats()["rebinds"] == 0


async def test_a_small_node_refuses_a_channel_it_cannot_buffer(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2, max_event=64) as small:
        await pub.advertise("map", max_size=4000)
        with pytest.raises(PayloadTooLarge, match=r"up to 4096 bytes.*at most 64"):
            await small.subscribe("map")
        await eventually(lambda: name_to_uid("map") not in ecb.subscribers)
        await small.subscribe("pose")  # one it can buffer
        await pub.publish("pose", bytes(60))
        assert small.stats()["refused_large"] == 1


async def test_two_publishers_interleave_on_one_channel(bus: str, ecb: CanEcb) -> None:
    async with (
        Node(can=bus, node_id=1) as a,
        Node(can=bus, node_id=2) as b,
        Node(can=bus, node_id=3) as listener,
    ):
        sub = await listener.subscribe("shared", maxlen=200)
        await a.advertise("shared", max_size=1000)
        await b.advertise("shared", max_size=1000)
        sent = {os.urandom(500 + i) for i in range(40)}
        order = list(sent)
        # both send at once: their frames interleave on the bus (virtual: in send order)
        await asyncio.gather(
            *(node.publish("shared", data) for node, data in zip([a, b] * 20, order, strict=True))
        )
        got = {(await sub.get_msg(timeout=5)).data for _ in order}
        assert got == sent
        assert listener.stats()["large_lost"] == 0


async def test_lost_repeated_or_foreign_frames_never_make_an_event(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as sub_node:
        sub = await sub_node.subscribe("frag", maxlen=100)
        await pub.advertise("frag", max_size=200)
        etag, txnode = etag_of(pub, "frag"), pub.stats()["txnode"]
        can_id = p.make_id(0x80, txnode, etag)
        event = os.urandom(100)

        def frames(tid: int) -> list[bytes]:  # a sender counts its transfer ids up
            return t.segment(event, tid, 8)

        def inject(data: list[bytes]) -> None:
            for d in data:
                raw_bus.send(can.Message(arbitration_id=can_id, data=d, is_extended_id=True))

        inject(frames(1)[:5] + frames(1)[6:])  # one lost
        inject([*frames(2)[:5], frames(2)[4], *frames(2)[5:]])  # one repeated
        inject([*frames(3)[:5], frames(3)[6], frames(3)[5], *frames(3)[7:]])  # two swapped
        inject(frames(4)[1:])  # the first lost
        inject([bytes([t.START | t.END | t.TOGGLE | 5, 0, 200]) + bytes(5)])  # says 200, has 5
        inject(frames(6))  # intact, at last
        msg = await sub.get_msg(timeout=5)
        assert msg.data == event
        assert sub.pending == 0
        await eventually(lambda: sub_node.stats()["large_lost"] == 5)  # each one, once


async def test_an_unfinished_transfer_is_counted_when_it_goes_stale(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    async with Node(can=bus, node_id=1) as pub, Node(can=bus, node_id=2) as sub_node:
        await sub_node.subscribe("stale")
        await pub.advertise("stale", max_size=200)
        can_id = p.make_id(0x80, pub.stats()["txnode"], etag_of(pub, "stale"))
        for d in t.segment(os.urandom(150), 0, 8)[:-1]:  # the last frame never comes
            raw_bus.send(can.Message(arbitration_id=can_id, data=d, is_extended_id=True))
        await eventually(
            lambda: sub_node.stats()["large_lost"] == 1, timeout=t.TRANSFER_TIMEOUT * 5
        )


async def test_too_large_is_a_clear_error(bus: str, ecb: CanEcb) -> None:
    async with Node(can=bus, node_id=1) as pub:
        with pytest.raises(PayloadTooLarge, match="at most 65535"):
            await pub.publish("huge", bytes(65536))
        with pytest.raises(ConfigError, match="at most 255 frames"):
            await pub.declare("huge", period_ms=1000, deadline_ms=1000, size_bytes=4096)


async def test_a_large_real_time_channel_is_admitted_by_its_frames(
    bus: str, tmp_path: Path
) -> None:
    async with (
        running_ecb(bus, tmp_path / "rt.db", bitrate=500_000, recovery=0.1) as ecb,
        Node(can=bus, node_id=1) as pub,
    ):
        # 100 bytes = 15 classic frames of 160 bits at most: 4.8 ms per event at 500 kbit/s
        priority = await pub.declare("scan", period_ms=20, deadline_ms=10, size_bytes=100)
        assert p.FIRST_EVENT_PRIORITY <= priority < p.DEFAULT_PRIORITY
        spec = next(iter(ecb._admission.declared.values()))
        assert spec.frames == 15
        from ups import Unschedulable

        with pytest.raises(Unschedulable):  # 15 frames every 5 ms do not fit beside it
            await pub.declare("scan2", period_ms=5, deadline_ms=5, size_bytes=100)
