"""``JausHost`` on a CAN node (virtual bus, a real CAN-ECB), driven over real UDP by a JAUS
OCU written here from the public message definitions (docs/jaus.md's sources), not with the
project's codec."""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from ups import Node
from ups.broker.can_ecb import CanEcb
from ups.jaus import JausId
from ups.jaus._host import JausHost
from ups.jaus._mapping import load_mapping

from .conftest import eventually
from .procs import ROOT

ROBOT = (1, 1, 1)  # subsystem.node.component
REQUEST_CONTROL, RELEASE_CONTROL, CONFIRM_CONTROL, REJECT_CONTROL = 0x000D, 0x000E, 0x000F, 0x0010
QUERY_CONTROL, REPORT_CONTROL = 0x200D, 0x400D
QUERY_HEARTBEAT, REPORT_HEARTBEAT = 0x2202, 0x4202
SET_WRENCH_EFFORT = 0x0405
RESUME = 0x0004


def jaus_id(subsystem: int, node: int, component: int) -> bytes:
    return struct.pack("<I", subsystem << 16 | node << 8 | component)


def judp(source: tuple[int, int, int], code: int, payload: bytes = b"", seq: int = 0) -> bytes:
    """One JUDP datagram: version 2; message type 0; data size (the message from its first
    byte to its sequence number); properties: priority standard (1), no broadcast, no ACK/NAK,
    a single message; destination, source; the code, payload and sequence number."""
    body = jaus_id(*ROBOT) + jaus_id(*source) + struct.pack("<H", code) + payload
    size = 1 + 2 + 1 + len(body) + 2
    return bytes((2, 0)) + struct.pack("<HB", size, 0x01) + body + struct.pack("<H", seq)


def parse(datagram: bytes) -> tuple[int, bytes, tuple[int, int, int]]:
    assert datagram[0] == 2
    size = struct.unpack_from("<H", datagram, 2)[0]
    dest = struct.unpack_from("<I", datagram, 5)[0]
    code = struct.unpack_from("<H", datagram, 13)[0]
    payload = datagram[15 : 1 + size - 2]
    return code, payload, (dest >> 16, dest >> 8 & 0xFF, dest & 0xFF)


def effort(percent: float) -> bytes:
    """Set Wrench Effort with only propulsive linear x: presence vector bit 0, then the value
    as an unsigned 16-bit scaled integer over [-100, 100] %."""
    return struct.pack("<HH", 0x0001, round((percent + 100) / 200 * 0xFFFF))


class Ocu:
    def __init__(self, address: tuple[str, int], me: tuple[int, int, int]) -> None:
        self.address, self.me = address, me
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)

    async def ask(self, code: int, payload: bytes = b"") -> tuple[int, bytes]:
        loop = asyncio.get_running_loop()
        await loop.sock_sendto(self.sock, judp(self.me, code, payload), self.address)
        async with asyncio.timeout(5):
            data = await loop.sock_recv(self.sock, 65536)
        code, body, to = parse(data)
        assert to == self.me
        return code, body

    async def send(self, code: int, payload: bytes) -> None:
        loop = asyncio.get_running_loop()
        await loop.sock_sendto(self.sock, judp(self.me, code, payload), self.address)


@pytest.fixture
async def robot(bus: str, ecb: CanEcb) -> AsyncIterator[tuple[JausHost, tuple[str, int], Node]]:
    bridge = load_mapping(ROOT / "examples" / "robot.jaus.toml")
    async with Node(can=bus, node_id=0x1A) as face_node, Node(can=bus, node_id=0x1B) as wheels:
        host = JausHost(face_node, bridge, JausId(*ROBOT), control_timeout=1.0)
        address = await host.start("127.0.0.1", 0)
        yield host, address, wheels
        host.close()


async def test_an_ocu_takes_control_and_drives_a_can_node(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, wheels = robot
    limit = await wheels.subscribe("robot/max-speed")
    first, second = Ocu(address, (2, 1, 1)), Ocu(address, (3, 1, 1))
    assert await first.ask(QUERY_HEARTBEAT) == (REPORT_HEARTBEAT, b"")
    await first.send(SET_WRENCH_EFFORT, effort(50))  # no control yet: refused, counted
    assert await first.ask(REQUEST_CONTROL, bytes([10])) == (CONFIRM_CONTROL, bytes([0]))
    assert await second.ask(REQUEST_CONTROL, bytes([5])) == (CONFIRM_CONTROL, bytes([1]))
    code, body = await second.ask(QUERY_CONTROL)
    # the holder (subsystem u16, node, component) and its authority
    assert (code, body) == (REPORT_CONTROL, struct.pack("<HBBB", 2, 1, 1, 10))
    await second.send(SET_WRENCH_EFFORT, effort(-20))  # not the holder: refused
    await first.send(SET_WRENCH_EFFORT, effort(40))  # the holder, but still in Standby: refused
    await first.send(RESUME, b"")
    await first.send(SET_WRENCH_EFFORT, effort(50))
    msg = await limit.get_msg(timeout=5)  # 50 % of full: 100 cm/s, big-endian i16
    assert msg.data == struct.pack(">h", 100)
    assert await first.ask(RELEASE_CONTROL) == (REJECT_CONTROL, bytes([0]))
    await first.send(SET_WRENCH_EFFORT, effort(80))  # released: refused again
    assert await first.ask(QUERY_HEARTBEAT) == (REPORT_HEARTBEAT, b"")  # all handled by now
    with pytest.raises(TimeoutError):
        await limit.get_msg(timeout=0.3)
    stats = host.stats()
    assert stats["commands"] == 1 and stats["refused_without_control"] == 3
    assert stats["refused_not_ready"] == 1
    assert stats["control_granted"] == 1 and stats["control_refused"] == 1


async def test_control_lapses_and_junk_is_counted(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, _ = robot
    first, second = Ocu(address, (2, 1, 1)), Ocu(address, (3, 1, 1))
    assert await first.ask(REQUEST_CONTROL, bytes([10])) == (CONFIRM_CONTROL, bytes([0]))
    host.component.access.heard -= 2.0  # silent past the 1 s timeout
    assert await second.ask(REQUEST_CONTROL, bytes([5])) == (CONFIRM_CONTROL, bytes([0]))
    loop = asyncio.get_running_loop()
    for junk in (b"", b"\x02", b"JAUS01.0", bytes(range(40)), b"\x02\x00\xff\xff"):
        await loop.sock_sendto(first.sock, junk, address)
    assert await first.ask(QUERY_HEARTBEAT) == (REPORT_HEARTBEAT, b"")  # still serving
    assert host.stats()["malformed"] == 5


@pytest.mark.netns
def test_ups_jaus_as_a_process_drives_a_can_node_in_another(tmp_path: object) -> None:
    """``ups jaus`` on the robot's bus (udp_multicast), a CAN node as another process, and the
    OCU over UDP: control, then Set Wrench Effort reaches the CAN node converted."""
    import json

    from .procs import Proc, private_multicast_bus

    bus = private_multicast_bus()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    mapping = str(ROOT / "examples" / "robot.jaus.toml")
    with (
        Proc("can-broker", "--can", bus, "--db", f"{tmp_path}/ecb.db", "--recovery", "0.2"),
        Proc("sub", "robot/max-speed", "--can", bus, "--json", "--count", "1", "--timeout",
             "60") as wheels,
        Proc("jaus", "--listen", f"127.0.0.1:{port}", "--id", "1.1.1", "--map", mapping,
             "--can", bus) as component,
    ):  # fmt: skip
        wheels.wait_for_line("subscribed to")
        component.wait_for_line("JAUS component 1.1.1 on 127.0.0.1")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as ocu:
            ocu.settimeout(5)
            ocu.sendto(judp((2, 1, 1), REQUEST_CONTROL, bytes([10])), ("127.0.0.1", port))
            code, body, _ = parse(ocu.recv(65536))
            assert (code, body) == (CONFIRM_CONTROL, bytes([0]))
            ocu.sendto(judp((2, 1, 1), RESUME), ("127.0.0.1", port))
            ocu.sendto(judp((2, 1, 1), SET_WRENCH_EFFORT, effort(25)), ("127.0.0.1", port))
        code, out = wheels.finish(timeout=60)
        assert code == 0
        (event,) = [json.loads(line) for line in out.splitlines()]
        assert event["data"] == struct.pack(">h", 50).hex()  # 25 % of full: 50 cm/s


QUERY_IDENTIFICATION, REPORT_IDENTIFICATION = 0x2B00, 0x4B00
QUERY_GLOBAL_POSE, REPORT_GLOBAL_POSE = 0x2402, 0x4402


async def test_queries_are_answered_from_the_latest_event(
    bus: str, ecb: CanEcb, tmp_path: Path
) -> None:
    from .test_jaus_mapping import GOOD, write

    bridge = load_mapping(write(tmp_path, GOOD))
    async with Node(can=bus, node_id=0x1C) as face_node, Node(can=bus, node_id=0x1D) as gps:
        host = JausHost(face_node, bridge, JausId(*ROBOT), name="rover")
        address = await host.start("127.0.0.1", 0)
        try:
            ocu = Ocu(address, (2, 1, 1))
            code, body = await ocu.ask(QUERY_IDENTIFICATION, bytes([4]))  # of the component
            # query type, identification type 60001 (component), string length, the name
            assert (code, body) == (
                REPORT_IDENTIFICATION,
                struct.pack("<BHB", 4, 60001, 5) + b"rover",
            )
            await ocu.send(QUERY_GLOBAL_POSE, struct.pack("<H", 0x01FF))  # no fix yet: counted
            pose = bridge["ReportGlobalPose"].channel
            await gps.publish("robot/pose", pose.encode({"lat": 48.4, "lon": 9.95, "heading": 0}))
            await eventually(lambda: "ReportGlobalPose" in host.component.latest)
            code, body = await ocu.ask(QUERY_GLOBAL_POSE, struct.pack("<H", 0x01FF))
            assert code == REPORT_GLOBAL_POSE
            presence, lat, lon = struct.unpack_from("<HII", body)
            assert presence & 0b11 == 0b11  # latitude and longitude present
            # unsigned 32-bit scaled integers over [-90, 90] and [-180, 180] degrees
            assert -90 + lat * 180 / 0xFFFFFFFF == pytest.approx(48.4, abs=1e-6)
            assert -180 + lon * 360 / 0xFFFFFFFF == pytest.approx(9.95, abs=1e-6)
            assert host.stats()["not_yet"] == 1
        finally:
            host.close()


async def test_velocity_state_from_the_wheels_and_wrench_effort_from_the_last_command(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    """The demo mapping: Query Velocity State from robot/speed (cm/s -> m/s), and Query Wrench
    Effort answered with the last Set Wrench Effort carried out."""
    host, address, wheels = robot
    first = Ocu(address, (2, 1, 1))
    await wheels.publish("robot/speed", struct.pack(">h", 150))  # 150 cm/s
    await eventually(lambda: "ReportVelocityState" in host.component.latest)
    code, body = await first.ask(0x2404, struct.pack("<H", 0x0001))  # velocity x only
    presence, raw = struct.unpack("<HI", body)
    # presence bit 0, u32 scaled over [-327.68, 327.67] m/s
    assert code == 0x4404 and presence == 1
    assert -327.68 + raw * 655.35 / 0xFFFFFFFF == pytest.approx(1.5, abs=1e-6)
    await first.send(0x2405, struct.pack("<H", 0xFFFF))  # no command yet: counted, unanswered
    assert await first.ask(REQUEST_CONTROL, bytes([10])) == (CONFIRM_CONTROL, bytes([0]))
    await first.send(RESUME, b"")
    await first.send(SET_WRENCH_EFFORT, effort(30))
    code, body = await first.ask(0x2405, struct.pack("<H", 0xFFFF))
    assert code == 0x4405 and body == effort(30)  # Report Wrench Effort: the same record
    assert host.stats()["not_yet"] == 1


IGVC_MOBILITY = ("PrimitiveDriver", "GlobalPoseSensor", "LocalPoseSensor", "VelocityStateSensor",
                 "LocalWaypointDriver", "LocalWaypointListDriver", "ListManager")  # fmt: skip


def ra33(code: int, component: int, payload: bytes = b"") -> bytes:
    """Paper 001's framing: "JAUS01.0", properties (priority 6, version 2 in bits 8-13), the
    code, the destination (instance 1, ``component``, node 1, subsystem 1), the source
    (instance 1, component 1, node 1, subsystem 42), data control (the data size), sequence
    number 0; then the data."""
    header = struct.pack("<HH", 6 | 2 << 8, code) + bytes((1, component, 1, 1, 1, 1, 1, 42))
    return b"JAUS01.0" + header + struct.pack("<HH", len(payload), 0) + payload


async def test_the_demo_robot_offers_the_igvc_profile_and_answers_ra33_at_its_service_ids(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    """Report Services lists every IGVC mobility service; an RA 3.3 OCU, which addresses a
    service as a component of its own (RA 3.3's ids: 33 Primitive Driver, 38 Global Pose
    Sensor, 41 Local Pose Sensor, ...), is answered from the id it asked; an id of a service
    not offered is not this component's."""
    host, address, gps = robot
    uris = {uri for uri, _, _ in host.component.services()}
    assert {f"urn:jaus:jss:mobility:{name}" for name in IGVC_MOBILITY} <= uris
    assert host.ra33_ids == {1, 33, 38, 41, 42, 46}
    fix = host.component.bridge["ReportGlobalPose"].channel
    await gps.publish("robot/global-pose", fix.encode({"lat": 48.4, "lon": 9.95, "yaw": 0.5,
                                                      "rms": 0.71}))  # fmt: skip
    await eventually(lambda: "ReportGlobalPose" in host.component.latest)
    loop = asyncio.get_running_loop()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setblocking(False)
        await loop.sock_sendto(sock, ra33(0x2402, 38, struct.pack("<H", 0x01FF)), address)
        async with asyncio.timeout(5):
            data = await loop.sock_recv(sock, 65536)
        assert struct.unpack_from("<H", data, 10)[0] == 0x4402  # Report Global Pose
        assert tuple(data[16:20]) == (1, 38, 1, 1)  # from the Global Pose Sensor
        (lat,) = struct.unpack_from("<i", data, 26)  # signed, over [-90, 90] (OpenJAUS)
        assert lat * 180 / 4294967294 == pytest.approx(48.4, abs=1e-6)
        before = host.stats()["not_for_me"]
        await loop.sock_sendto(sock, ra33(0x2202, 50, b""), address)  # a Range Sensor: no
        await loop.sock_sendto(sock, ra33(0x2202, 33, b""), address)  # the Primitive Driver
        async with asyncio.timeout(5):
            data = await loop.sock_recv(sock, 65536)
        assert struct.unpack_from("<H", data, 10)[0] == 0x4202  # Report Heartbeat Pulse
        assert tuple(data[16:20]) == (1, 33, 1, 1)
    assert host.stats()["not_for_me"] == before + 1


def judp_part(source: tuple[int, int, int], flags: int, data: bytes, seq: int) -> bytes:
    """One part of a large JUDP message: data flags (1 first, 3 last) in bits 6-7 of the
    properties; ``data`` is the part's share of the code and payload."""
    body = jaus_id(*ROBOT) + jaus_id(*source) + data
    size = 1 + 2 + 1 + len(body) + 2
    return (
        bytes((2, 0)) + struct.pack("<HB", size, 0x01 | flags << 6) + body + struct.pack("<H", seq)
    )


async def test_the_controllers_id_from_another_address_is_refused_in_every_framing(
    robot: tuple[JausHost, tuple[str, int], Node],
) -> None:
    """An RA 3.3 OCU (42.1.1) controls the component. The same id from other sockets: an RA 3.3
    Request Control is told Not Available (from the service it asked); the parts of a JUDP
    Set Wrench Effort are dropped before reassembly; a Set Emergency is taken (anyone may stop
    the robot) but the Clear Emergency is not; every refusal is counted."""
    host, address, _ = robot
    loop = asyncio.get_running_loop()

    async def ask(sock: socket.socket, datagram: bytes) -> bytes:
        await loop.sock_sendto(sock, datagram, address)
        async with asyncio.timeout(5):
            return await loop.sock_recv(sock, 65536)

    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as impostor,
    ):
        for sock in (holder, impostor):
            sock.bind(("127.0.0.1", 0))
            sock.setblocking(False)
        answer = await ask(holder, ra33(REQUEST_CONTROL, 33, bytes([10])))
        assert struct.unpack_from("<H", answer, 10)[0] == CONFIRM_CONTROL and answer[24] == 0
        where = holder.getsockname()
        assert host.component.access.holder_address == where
        answer = await ask(impostor, ra33(REQUEST_CONTROL, 33, bytes([200])))
        assert struct.unpack_from("<H", answer, 10)[0] == CONFIRM_CONTROL
        assert answer[24] == 1 and tuple(answer[16:20]) == (1, 33, 1, 1)  # Not Available
        message = struct.pack("<H", SET_WRENCH_EFFORT) + effort(90)
        for flags, data, seq in ((1, message[:3], 20), (3, message[3:], 21)):
            await loop.sock_sendto(impostor, judp_part((42, 1, 1), flags, data, seq), address)
        await loop.sock_sendto(
            impostor, judp((42, 1, 1), 0x0006, b"\x01\x00"), address
        )  # Set Emergency: stop
        await loop.sock_sendto(
            impostor, judp((42, 1, 1), 0x0007, b"\x01\x00"), address
        )  # Clear Emergency
        assert (await ask(impostor, judp((3, 1, 1), QUERY_HEARTBEAT)))[13] == 0x02  # all handled
    stats = host.stats()
    assert stats["refused_other_address"] == 4  # Request Control, two parts, Clear Emergency
    assert host._reassembler.counts.parts_in == 0  # the parts were never held
    assert host.component.access.state.name == "EMERGENCY"  # the stop was taken
    assert host.component.access.holder_address == where  # still the holder's
