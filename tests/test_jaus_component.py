"""The JAUS component host in one process (a virtual CAN bus, a real CAN-ECB, real UDP), driven
with the project's codec: events and their bounds, Management, emergencies, discovery,
acknowledgements, the client table's bound, and 10^5 fuzzed datagrams that must not stop a
legitimate OCU from being served."""

from __future__ import annotations

import asyncio
import random
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from ups import Node, jaus
from ups.broker.can_ecb import CanEcb
from ups.jaus import AckNak, JausId, JudpHeader, JudpMessage
from ups.jaus._events import MAX_EVENTS
from ups.jaus._host import JausHost
from ups.jaus._mapping import load_mapping

from .conftest import eventually
from .test_jaus_mapping import GOOD, write

ROBOT = JausId(1, 1, 1)


class Ocu:
    def __init__(self, address: tuple[str, int], me: JausId) -> None:
        self.address, self.me, self.seq = address, me, 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)

    def close(self) -> None:
        self.sock.close()

    async def send(self, payload: Any, *, to: JausId = ROBOT, ack: bool = False) -> None:
        code, body = jaus.encode_payload(payload)
        self.seq += 1
        header = JudpHeader(destination=to, source=self.me, sequence=self.seq,
                            ack_nak=AckNak.REQUEST if ack else AckNak.NONE)  # fmt: skip
        datagram = jaus.encode_judp([JudpMessage(header, code, body)])
        await asyncio.get_running_loop().sock_sendto(self.sock, datagram, self.address)

    async def receive(self) -> JudpMessage:
        async with asyncio.timeout(5):
            data = await asyncio.get_running_loop().sock_recv(self.sock, 65536)
        (message,) = jaus.decode_judp(data)
        assert message.header.destination == self.me
        return message

    async def next(self, kind: type) -> Any:
        while True:
            message = await self.receive()
            if message.code is not None:
                payload = jaus.decode_payload(message.code, message.payload)
                if isinstance(payload, kind):
                    return payload

    async def ask(self, payload: Any, kind: type) -> Any:
        await self.send(payload)
        return await self.next(kind)


@pytest.fixture
async def robot(
    bus: str, ecb: CanEcb, tmp_path: Path
) -> AsyncIterator[tuple[JausHost, tuple[str, int], Node]]:
    bridge = load_mapping(write(tmp_path, GOOD))
    async with Node(can=bus, node_id=0x2A) as face_node, Node(can=bus, node_id=0x2B) as gps:
        host = JausHost(face_node, bridge, ROBOT, name="rover", max_clients=8)
        address = await host.start("127.0.0.1", 0)
        yield host, address, gps
        host.close()


async def publish_fix(host: JausHost, gps: Node, lat: float) -> None:
    pose = host.component.bridge["ReportGlobalPose"].channel
    before = host.component.latest.get("ReportGlobalPose")
    data = pose.encode({"lat": lat, "lon": 9.95, "heading": 0})
    await gps.publish("robot/pose", data)
    await eventually(lambda: host.component.latest.get("ReportGlobalPose") not in (None, before))


def latitude(event: jaus.Event) -> float:
    report = jaus.decode_payload(int.from_bytes(event.report_message[:2], "little"),
                                 event.report_message[2:])  # fmt: skip
    assert isinstance(report, jaus.ReportGlobalPose) and report.latitude is not None
    return report.latitude


QUERY_POSE = (0x2402).to_bytes(2, "little") + jaus.QueryGlobalPose(0x0001).to_bytes()


async def test_every_change_events_carry_each_new_fix_and_cancel(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, gps = robot
    ocu = Ocu(address, JausId(2, 1, 1))
    await publish_fix(host, gps, 10.0)
    confirm = await ocu.ask(jaus.CreateEvent(1, jaus.EventType.EVERY_CHANGE, 0, QUERY_POSE),
                            jaus.ConfirmEventRequest)  # fmt: skip
    assert confirm.request_id == 1
    assert latitude(await ocu.next(jaus.Event)) == pytest.approx(10.0, abs=1e-6)  # at once
    for lat in (11.0, 12.0):
        await publish_fix(host, gps, lat)
        assert latitude(await ocu.next(jaus.Event)) == pytest.approx(lat, abs=1e-6)
    cancel = await ocu.ask(jaus.CancelEvent(2, confirm.event_id), jaus.ConfirmEventRequest)
    assert cancel.event_id == confirm.event_id and not host.component.events.table
    reject = await ocu.ask(jaus.CancelEvent(3, confirm.event_id), jaus.RejectEventRequest)
    assert reject.response_code == jaus.EventRejection.INVALID_EVENT_ID
    ocu.close()


async def test_events_are_bounded_and_refused_clearly(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, _ = robot
    ocu = Ocu(address, JausId(2, 1, 1))
    unknown = (0x2416).to_bytes(2, "little") + bytes(1)  # Query Acceleration Limit: not here
    reject = await ocu.ask(jaus.CreateEvent(1, jaus.EventType.PERIODIC, 5, unknown),
                           jaus.RejectEventRequest)  # fmt: skip
    assert reject.response_code == jaus.EventRejection.MESSAGE_UNSUPPORTED
    heartbeat = (0x2202).to_bytes(2, "little")
    for n in range(MAX_EVENTS):
        confirm = await ocu.ask(jaus.CreateEvent(n % 256, jaus.EventType.PERIODIC, 2000.0 / 2,
                                                 heartbeat), jaus.ConfirmEventRequest)  # fmt: skip
        assert confirm.confirmed_periodic_rate <= 25.1  # capped at MAX_RATE
    reject = await ocu.ask(jaus.CreateEvent(9, jaus.EventType.PERIODIC, 1, heartbeat),
                           jaus.RejectEventRequest)  # fmt: skip
    assert reject.response_code == jaus.EventRejection.CONNECTION_REFUSED
    assert host.stats()["events_refused"] == 1 and host.stats()["events"] == MAX_EVENTS
    host.component.forget(ocu.me)  # the client goes: its events with it
    assert host.stats()["events"] == 0
    ocu.close()


async def test_management_emergency_and_discovery(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, _ = robot
    ocu, bystander = Ocu(address, JausId(2, 1, 1)), Ocu(address, JausId(3, 1, 1))
    status = await ocu.ask(jaus.QueryStatus(), jaus.ReportStatus)
    assert status.status == jaus.ManagementStatus.STANDBY
    await ocu.send(jaus.Resume())  # without control: refused
    assert (await ocu.ask(jaus.QueryStatus(), jaus.ReportStatus)).status == 2
    assert (await ocu.ask(jaus.RequestControl(5), jaus.ConfirmControl)).response == 0
    await ocu.send(jaus.Resume())
    assert (await ocu.ask(jaus.QueryStatus(), jaus.ReportStatus)).status == 1  # READY
    await bystander.send(jaus.SetEmergency(1))  # anyone may stop the robot
    assert (await ocu.ask(jaus.QueryStatus(), jaus.ReportStatus)).status == 5
    await ocu.send(jaus.SetWrenchEffort(propulsive_linear_x=10))
    await ocu.send(jaus.ClearEmergency(1))  # only who set it clears it
    assert (await ocu.ask(jaus.QueryStatus(), jaus.ReportStatus)).status == 5
    await bystander.send(jaus.ClearEmergency(1))
    assert (await ocu.ask(jaus.QueryStatus(), jaus.ReportStatus)).status == 1  # back to READY
    assert host.stats()["refused_in_emergency"] == 1
    services = await ocu.ask(jaus.QueryServices(), jaus.ReportServices)
    uris = {s.uri for s in services.nodes[0].components[0].services}
    assert {"urn:jaus:jss:core:Events", "urn:jaus:jss:core:Management",
            "urn:jaus:jss:mobility:GlobalPoseSensor"} <= uris  # fmt: skip
    config = await ocu.ask(jaus.QueryConfiguration(2), jaus.ReportConfiguration)
    assert config.nodes == (jaus.NodeEntry(1, (jaus.ComponentEntry(1, 1),)),)
    await ocu.send(jaus.Shutdown())
    assert (await ocu.next(jaus.RejectControl)).response == jaus.RejectResponse.CONTROL_RELEASED
    await asyncio.wait_for(host.finished.wait(), 5)
    assert (await ocu.ask(jaus.RequestControl(200), jaus.ConfirmControl)).response == 1
    ocu.close()
    bystander.close()


async def test_acks_broadcasts_strangers_and_the_client_bound(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, _ = robot
    ocu = Ocu(address, JausId(2, 1, 1))
    await ocu.send(jaus.QueryHeartbeatPulse(), ack=True)
    replies = [await ocu.receive(), await ocu.receive()]
    acks = [m for m in replies if m.header.ack_nak == AckNak.ACK]
    assert len(acks) == 1 and acks[0].header.sequence == ocu.seq and acks[0].code is None
    await ocu.send(jaus.QueryHeartbeatPulse(), to=JausId(7, 7, 7))  # another component's
    await ocu.send(jaus.QueryHeartbeatPulse(), to=JausId(0xFFFF, 0xFF, 0xFF))  # everyone's
    assert isinstance(await ocu.next(jaus.ReportHeartbeatPulse), jaus.ReportHeartbeatPulse)
    assert host.stats()["not_for_me"] == 1
    assert (await ocu.ask(jaus.RequestControl(5), jaus.ConfirmControl)).response == 0
    strangers = [Ocu(address, JausId(50 + n, 1, 1)) for n in range(12)]
    for stranger in strangers:
        await stranger.ask(jaus.QueryHeartbeatPulse(), jaus.ReportHeartbeatPulse)
    assert len(host.clients) == 8 and host.stats()["clients_evicted"] == 5
    assert ocu.me in host.clients  # the controlling client is never evicted
    for stranger in strangers:
        stranger.close()
    ocu.close()


async def test_a_hundred_thousand_fuzzed_datagrams_do_not_stop_the_component(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, gps = robot
    ocu = Ocu(address, JausId(2, 1, 1))
    await publish_fix(host, gps, 20.0)
    # the highest authority: no forged request may take control away
    assert (await ocu.ask(jaus.RequestControl(255), jaus.ConfirmControl)).response == 0
    rng = random.Random(16)
    seeds = [
        jaus.encode_judp([JudpMessage(JudpHeader(ROBOT, JausId(9, 9, 9)), code, body)])
        for code, body in (
            jaus.encode_payload(jaus.CreateEvent(1, jaus.EventType.PERIODIC, 10, QUERY_POSE)),
            jaus.encode_payload(jaus.RequestControl(255)),
            jaus.encode_payload(jaus.SetWrenchEffort(propulsive_linear_x=5)),
            jaus.encode_payload(jaus.QueryGlobalPose(0xFFFF)),
        )
    ] + [b"JAUS01.0" + bytes(16)]
    fuzz = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fuzz.bind(("127.0.0.1", 0))
    for n in range(100_000):
        data = bytearray(rng.choice(seeds))
        for _ in range(rng.randint(1, 4)):  # flip, cut or extend
            where = rng.randrange(len(data))
            data[where] = rng.randrange(256)
        if n % 7 == 0:
            data = data[: rng.randrange(len(data))]
        fuzz.sendto(bytes(data), address)
        if n % 100 == 0:  # the answer comes after the host has read all sent before
            pose = await ocu.ask(jaus.QueryGlobalPose(0x0001), jaus.ReportGlobalPose)
            assert pose.latitude == pytest.approx(20.0, abs=1e-6)
    fuzz.close()
    stats = host.stats()
    assert stats["handler_errors"] == 0
    assert stats["malformed"] > 10_000
    assert host.component.access.holder == ocu.me  # nobody took control from garbage
    assert len(host.component.events.table) <= MAX_EVENTS
    ocu.close()


def test_ups_demo_with_a_jaus_face_obeys_an_ocu() -> None:
    """``ups demo --jaus``: the commands it prints work, and the wheel encoder obeys."""
    import json
    import re
    import time

    from .procs import Proc

    with Proc("demo", "--jaus", "127.0.0.1:0", "--duration", "20") as demo:
        deadline, target = time.monotonic() + 30, None
        while target is None and time.monotonic() < deadline:
            found = re.search(r"--target (127\.0\.0\.1:\d+)", "".join(demo.stdout_lines))
            target = found.group(1) if found else None
            time.sleep(0.05)  # polling the reader thread's lines, not waiting for an effect
        assert target is not None, "".join(demo.stdout_lines + demo.stderr_lines)
        with Proc("jaus-ocu", "--target", target, "send", "SetWrenchEffort",
                  "propulsive_linear_x=20", "--control") as ocu:  # fmt: skip
            code, out = ocu.finish(timeout=30)
        assert code == 0 and json.loads(out.splitlines()[-1]) == {"sent": "SetWrenchEffort"}
        deadline = time.monotonic() + 30
        while "speed limit 40 cm/s" not in "".join(demo.stdout_lines):
            assert time.monotonic() < deadline, "".join(demo.stdout_lines)
            time.sleep(0.05)


async def test_the_components_counters_show_in_ups_status(tmp_path: Path) -> None:
    """On a TCP/IP node, ``ups status`` of the node carries the component as ``jaus``."""
    from ups._tcpface import query_status

    from .test_tcp_node import running_tcp_ecb

    bridge = load_mapping(write(tmp_path, GOOD))
    async with running_tcp_ecb() as ecb, Node(broker=f"127.0.0.1:{ecb.port}") as node:
        host = JausHost(node, bridge, ROBOT)
        node.face.extra_status = host.status  # type: ignore[attr-defined]  # as ups jaus does
        address = await host.start("127.0.0.1", 0)
        ocu = Ocu(address, JausId(2, 1, 1))
        try:
            assert (await ocu.ask(jaus.RequestControl(5), jaus.ConfirmControl)).response == 0
            where, port = node.face.address  # type: ignore[attr-defined]
            info = (await query_status(f"{where}:{port}"))["jaus"]
            assert info["controller"] == "2.1.1" and info["state"] == "STANDBY"
            assert info["clients"][0]["id"] == "2.1.1"
            assert info["stats"]["control_granted"] == 1
        finally:
            ocu.close()
            host.close()
