"""``ups jaus`` as a process on a robot's CAN bus (udp_multicast) inside a private network
namespace, reached over a veth pair by an OCU written here from the public message definitions
(AS5669A, AS5710A core 1.1, AS6009 mobility, and RA 3.3 for paper 001's framing), not with the
project's codec: broadcast discovery, control, Resume, Set Wrench Effort reaching a CAN node
converted, Query Global Pose answered with the latest fix, a 10 Hz periodic event whose reports
carry the latest fix, a second OCU refused, commands refused after release."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import socket
import struct
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from .procs import Proc, private_multicast_bus

pytestmark = [pytest.mark.netns, pytest.mark.timeout(240)]

ROBOT_ADDR, OCU_ADDR, BROADCAST = "10.79.0.1", "10.79.0.2", "10.79.0.255"
JAUS_PORT = 3794
ROBOT = (1, 1, 1)

CATALOG = """
[channel."robot/max-speed"]
byte_order = "big"
fields = [{ name = "limit", type = "i16", unit = "cm/s" }]

[channel."robot/pose"]
fields = [{ name = "lat", type = "f64" }, { name = "lon", type = "f64" },
          { name = "heading", type = "f32" }]
"""
MAPPING = """
catalog = "catalog.toml"

[message.SetWrenchEffort]
channel = "robot/max-speed"
fields.propulsive_linear_x = { field = "limit", scale = 2.0 }

[message.ReportGlobalPose]
channel = "robot/pose"
rate = 20
fields.latitude = "lat"
fields.longitude = "lon"
fields.yaw = { field = "heading", scale = 57.29577951308232 }
ignore = ["altitude", "position_rms", "roll", "pitch", "attitude_rms", "timestamp"]
"""


_namespaces = itertools.count()


@contextlib.contextmanager
def robot_namespace() -> Iterator[tuple[str, ...]]:
    """A network namespace for the robot, joined to ours by a veth pair (10.79.0.0/24), with
    loopback multicast for its udp_multicast CAN bus; yields the prefix that runs a process
    there. Our own namespace must be the private one of scripts/netns-run."""
    private_multicast_bus()  # refuses (skips or fails) outside a private namespace
    if os.geteuid() != 0:
        pytest.skip("needs root: ip netns add and a veth pair")
    tag = f"{os.getpid() % 100000}x{next(_namespaces)}"  # a namespace lives on while its last
    ns, here, there = f"ups-jaus-{tag}", f"jo{tag}", f"jr{tag}"  # process ends: names anew
    subprocess.run(["ip", "netns", "add", ns], check=True)
    try:
        for cmd in (
            ["ip", "link", "add", here, "type", "veth", "peer", "name", there],
            ["ip", "link", "set", there, "netns", ns],
            ["ip", "addr", "add", f"{OCU_ADDR}/24", "broadcast", BROADCAST, "dev", here],
            ["ip", "link", "set", here, "up"],
            ["ip", "-n", ns, "addr", "add", f"{ROBOT_ADDR}/24", "broadcast", BROADCAST, "dev",
             there],
            ["ip", "-n", ns, "link", "set", there, "up"],
            ["ip", "-n", ns, "link", "set", "lo", "up", "multicast", "on"],
            ["ip", "-n", ns, "route", "add", "224.0.0.0/4", "dev", "lo"],
        ):  # fmt: skip
            subprocess.run(cmd, check=True)
        yield ("ip", "netns", "exec", ns)
    finally:
        subprocess.run(["ip", "link", "del", here], check=False, capture_output=True)  # both ends
        subprocess.run(["ip", "netns", "del", ns], check=False)


# --- the OCU, from the public definitions ---------------------------------------------------

REQUEST_CONTROL, RELEASE_CONTROL, CONFIRM_CONTROL, REJECT_CONTROL = 0x000D, 0x000E, 0x000F, 0x0010
RESUME, SET_WRENCH_EFFORT = 0x0004, 0x0405
CREATE_EVENT, CANCEL_EVENT, CONFIRM_EVENT_REQUEST, EVENT = 0x01F0, 0x01F2, 0x01F3, 0x41F1
QUERY_IDENTIFICATION, REPORT_IDENTIFICATION = 0x2B00, 0x4B00
QUERY_GLOBAL_POSE, REPORT_GLOBAL_POSE = 0x2402, 0x4402
QUERY_HEARTBEAT, REPORT_HEARTBEAT = 0x2202, 0x4202


def judp_id(subsystem: int, node: int, component: int) -> bytes:
    return struct.pack("<I", subsystem << 16 | node << 8 | component)


class JudpOcu:
    """AS5669A: version 2, then per message: type/HC byte 0, data size u16 (from that byte
    to the sequence number), properties (priority 1 | broadcast << 2 | ACK/NAK << 4 | data
    flags << 6), destination and source ids (u32: subsystem << 16 | node << 8 | component),
    the message code and payload, the sequence number u16. Little-endian throughout."""

    def __init__(self, me: tuple[int, int, int]) -> None:
        self.me, self.seq = me, 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        self.sock.bind((OCU_ADDR, 0))
        self.sock.settimeout(5)
        self.robot: tuple[str, int] = (BROADCAST, JAUS_PORT)

    def send(self, code: int, payload: bytes = b"", *, broadcast: bool = False) -> None:
        dest = judp_id(0xFFFF, 0xFF, 0xFF) if broadcast else judp_id(*ROBOT)
        body = dest + judp_id(*self.me) + struct.pack("<H", code) + payload
        props = 0x01 | (2 << 2 if broadcast else 0)  # standard priority; global broadcast
        size = 1 + 2 + 1 + len(body) + 2
        self.seq += 1
        datagram = bytes((2, 0)) + struct.pack("<HB", size, props) + body
        self.sock.sendto(datagram + struct.pack("<H", self.seq), self.robot)

    def receive(self) -> tuple[int, bytes, tuple[str, int]]:
        data, sender = self.sock.recvfrom(65536)
        assert data[0] == 2 and data[1] == 0
        size = struct.unpack_from("<H", data, 2)[0]
        assert len(data) == 1 + size  # one message per datagram here
        assert struct.unpack_from("<I", data, 5)[0] == struct.unpack("<I", judp_id(*self.me))[0]
        code = struct.unpack_from("<H", data, 13)[0]
        return code, data[15 : 1 + size - 2], sender

    def expect(self, code: int) -> bytes:
        """The payload of the next message with ``code`` (others, e.g. events, skipped)."""
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            got, payload, _ = self.receive()
            if got == code:
                return payload
        raise AssertionError(f"no message {code:#06x}")

    def ask(self, code: int, payload: bytes, answer: int) -> bytes:
        self.send(code, payload)
        return self.expect(answer)


def scaled(value: float, lower: float, upper: float, bits: int) -> int:
    return round((value - lower) / (upper - lower) * ((1 << bits) - 1))


def unscaled(raw: int, lower: float, upper: float, bits: int) -> float:
    return lower + raw * (upper - lower) / ((1 << bits) - 1)


def wrench(percent: float) -> bytes:
    """Set Wrench Effort, propulsive linear x only: presence vector u16 bit 0, u16 scaled
    over [-100, 100] %."""
    return struct.pack("<HH", 0x0001, scaled(percent, -100, 100, 16))


def pose_of(payload: bytes) -> tuple[float, float]:
    """Latitude and longitude of a Report Global Pose: presence vector u16, then u32 scaled
    over [-90, 90] and [-180, 180] degrees."""
    presence, lat, lon = struct.unpack_from("<HII", payload)
    assert presence & 0b11 == 0b11
    return unscaled(lat, -90, 90, 32), unscaled(lon, -180, 180, 32)


# --- the test ---------------------------------------------------------------------------------


def write_mapping(tmp_path: Path) -> Path:
    (tmp_path / "catalog.toml").write_text(CATALOG)
    mapping = tmp_path / "robot.jaus.toml"
    mapping.write_text(MAPPING)
    return mapping


def publish_fix(in_robot: tuple[str, ...], bus: str, catalog: Path, lat: float) -> None:
    with Proc("pub", "robot/pose", f"lat={lat},lon=9.95,heading=0", "--can", bus, "--catalog",
              str(catalog), prefix=in_robot) as pub:  # fmt: skip
        assert pub.finish(timeout=30)[0] == 0


def test_an_ocu_discovers_controls_queries_and_watches_the_robot_over_judp(
    tmp_path: Path,
) -> None:
    bus = private_multicast_bus()
    mapping = write_mapping(tmp_path)
    catalog = tmp_path / "catalog.toml"
    with robot_namespace() as in_robot, (
        Proc("can-broker", "--can", bus, "--db", f"{tmp_path}/ecb.db", "--recovery", "0.2",
             prefix=in_robot)
    ), Proc("sub", "robot/max-speed", "--can", bus, "--json", "--count", "2", "--timeout", "120",
            prefix=in_robot) as wheels, Proc(
        "jaus", "--listen", f"0.0.0.0:{JAUS_PORT}", "--id", "1.1.1", "--map", str(mapping),
        "--can", bus, "--name", "rover", prefix=in_robot,
    ) as component:  # fmt: skip
        wheels.wait_for_line("subscribed to")
        component.wait_for_line("JAUS component 1.1.1")
        publish_fix(in_robot, bus, catalog, 48.4)
        ocu, other = JudpOcu((2, 1, 1)), JudpOcu((3, 1, 1))

        # discovery by broadcast: who is out there?
        ocu.send(QUERY_IDENTIFICATION, bytes([4]), broadcast=True)
        code, payload, sender = ocu.receive()
        assert code == REPORT_IDENTIFICATION and sender == (ROBOT_ADDR, JAUS_PORT)
        # query type, type 60001 (component), count byte, the name
        assert payload == struct.pack("<BHB", 4, 60001, 5) + b"rover"
        ocu.robot = other.robot = sender

        # control: granted to the first, refused to the second
        assert ocu.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([0])
        assert other.ask(REQUEST_CONTROL, bytes([200 - 195]), CONFIRM_CONTROL) == bytes([1])
        ocu.send(RESUME)
        ocu.send(SET_WRENCH_EFFORT, wrench(25))  # 25 % of 200 cm/s

        # the latest fix, by query
        lat, lon = pose_of(ocu.ask(QUERY_GLOBAL_POSE, struct.pack("<H", 0x0003),
                                   REPORT_GLOBAL_POSE))  # fmt: skip
        assert (lat, lon) == (pytest.approx(48.4, abs=1e-6), pytest.approx(9.95, abs=1e-6))

        # a periodic event at 10 Hz on Query Global Pose: request id 7, type 0 (periodic),
        # rate u16 scaled over [0, 1092] Hz, the query message as count u32 + code + payload
        query = struct.pack("<HH", QUERY_GLOBAL_POSE, 0x0003)
        ocu.send(CREATE_EVENT, struct.pack("<BBHI", 7, 0, scaled(10, 0, 1092, 16), len(query))
                 + query)  # fmt: skip
        request_id, event_id, rate = struct.unpack("<BBH", ocu.expect(CONFIRM_EVENT_REQUEST))
        assert request_id == 7 and unscaled(rate, 0, 1092, 16) == pytest.approx(10, abs=0.02)

        def next_fix() -> float:
            # event id, sequence number, the report as count u32 + code + payload
            got_id, _, count, code = struct.unpack_from("<BBIH", payload := ocu.expect(EVENT))
            assert got_id == event_id and code == REPORT_GLOBAL_POSE
            assert count == len(payload) - 6
            return pose_of(payload[8:])[0]

        assert [next_fix() for _ in range(3)] == [pytest.approx(48.4, abs=1e-6)] * 3
        publish_fix(in_robot, bus, catalog, 48.5)
        fixes = [next_fix() for _ in range(20)]
        moved = fixes.index(pytest.approx(48.5, abs=1e-6))  # the new fix shows up, and stays
        assert fixes[moved:] == [pytest.approx(48.5, abs=1e-6)] * (20 - moved)
        ocu.send(CANCEL_EVENT, struct.pack("<BB", 8, event_id))
        assert ocu.expect(CONFIRM_EVENT_REQUEST)[:2] == bytes([8, event_id])

        # released: commands are refused. The proof is in the order: control is taken back
        # and one more command sent; the wheels' second event must be that one.
        assert ocu.ask(RELEASE_CONTROL, b"", REJECT_CONTROL) == bytes([0])
        ocu.send(SET_WRENCH_EFFORT, wrench(90))
        other.send(SET_WRENCH_EFFORT, wrench(80))  # never had control
        assert other.ask(QUERY_HEARTBEAT, b"", REPORT_HEARTBEAT) == b""  # handled by now
        assert ocu.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([0])
        ocu.send(RESUME)
        ocu.send(SET_WRENCH_EFFORT, wrench(10))
        code, out = wheels.finish(timeout=60)
        assert code == 0
        events = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
        assert [e["data"] for e in events] == [struct.pack(">h", v).hex() for v in (50, 20)]


class Ra33Ocu(JudpOcu):
    """Paper 001's framing: "JAUS01.0", then the 16-byte RA 3.3 header (OpenJAUS 3.3.1's byte
    order): message properties u16 (priority 6, version 2 in bits 8-13), command code u16,
    destination and source as instance, component, node, subsystem bytes, data control u16
    (data size in bits 0-11), sequence number u16; then the message data. One message per
    datagram; broadcast is 0xFF in every address byte."""

    def send(self, code: int, payload: bytes = b"", *, broadcast: bool = False) -> None:
        dest = bytes((0xFF,) * 4) if broadcast else bytes((1, ROBOT[2], ROBOT[1], ROBOT[0]))
        src = bytes((1, self.me[2], self.me[1], self.me[0]))
        self.seq += 1
        header = struct.pack("<HH", 6 | 2 << 8, code) + dest + src
        header += struct.pack("<HH", len(payload), self.seq)
        self.sock.sendto(b"JAUS01.0" + header + payload, self.robot)

    def receive(self) -> tuple[int, bytes, tuple[str, int]]:
        data, sender = self.sock.recvfrom(65536)
        assert data[:8] == b"JAUS01.0"
        props, code = struct.unpack_from("<HH", data, 8)
        assert props >> 8 & 0x3F == 2  # version 3.2/3.3
        assert tuple(data[12:16]) == (1, self.me[2], self.me[1], self.me[0])  # to us
        size = struct.unpack_from("<H", data, 20)[0] & 0x0FFF
        assert len(data) == 24 + size
        return code, data[24:], sender


def test_an_ra33_ocu_discovers_controls_queries_and_drives_the_robot(tmp_path: Path) -> None:
    """The same robot through paper 001's RA 3.3 framing, whose payloads differ: signed scaled
    integers (OpenJAUS jausShortFromDouble: (value - mid) / ((max - min) / 65534)), a Report
    Identification with an authority byte and no count, a Reject Component Control without
    data."""
    bus = private_multicast_bus()
    mapping = write_mapping(tmp_path)
    catalog = tmp_path / "catalog.toml"
    with robot_namespace() as in_robot, (
        Proc("can-broker", "--can", bus, "--db", f"{tmp_path}/ecb.db", "--recovery", "0.2",
             prefix=in_robot)
    ), Proc("sub", "robot/max-speed", "--can", bus, "--json", "--count", "2", "--timeout", "120",
            prefix=in_robot) as wheels, Proc(
        "jaus", "--listen", f"0.0.0.0:{JAUS_PORT}", "--id", "1.1.1", "--map", str(mapping),
        "--can", bus, "--name", "rover", prefix=in_robot,
    ) as component:  # fmt: skip
        wheels.wait_for_line("subscribed to")
        component.wait_for_line("JAUS component 1.1.1")
        publish_fix(in_robot, bus, catalog, -33.9)
        ocu, other = Ra33Ocu((42, 1, 1)), Ra33Ocu((43, 1, 1))

        def effort(percent: float) -> bytes:
            return struct.pack("<Hh", 0x0001, round(percent / (200 / 65534)))

        ocu.send(QUERY_IDENTIFICATION, bytes([4]), broadcast=True)
        code, payload, sender = ocu.receive()
        assert code == REPORT_IDENTIFICATION and sender == (ROBOT_ADDR, JAUS_PORT)
        # query type, authority, type 60001 (component), the name to the end
        assert payload == struct.pack("<BBH", 4, 0, 60001) + b"rover"
        ocu.robot = other.robot = sender

        assert ocu.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([0])
        assert other.ask(REQUEST_CONTROL, bytes([5]), CONFIRM_CONTROL) == bytes([1])
        ocu.send(RESUME)
        ocu.send(SET_WRENCH_EFFORT, effort(25))

        presence, lat, lon = struct.unpack_from(
            "<Hii", ocu.ask(QUERY_GLOBAL_POSE, struct.pack("<H", 0x0003), REPORT_GLOBAL_POSE)
        )
        assert presence & 0b11 == 0b11
        assert lat * 180 / 4294967294 == pytest.approx(-33.9, abs=1e-6)  # signed, mid 0
        assert lon * 360 / 4294967294 == pytest.approx(9.95, abs=1e-6)

        assert ocu.ask(RELEASE_CONTROL, b"", REJECT_CONTROL) == b""  # RA 3.3: no data
        ocu.send(SET_WRENCH_EFFORT, effort(90))
        other.send(SET_WRENCH_EFFORT, effort(80))
        assert other.ask(QUERY_HEARTBEAT, b"", REPORT_HEARTBEAT) == b""
        assert ocu.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([0])
        ocu.send(RESUME)
        ocu.send(SET_WRENCH_EFFORT, effort(10))
        code, out = wheels.finish(timeout=60)
        assert code == 0
        events = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
        assert [e["data"] for e in events] == [struct.pack(">h", v).hex() for v in (50, 20)]


def test_ups_jaus_ocu_discovers_queries_drives_and_watches(tmp_path: Path) -> None:
    """The project's own OCU, as a user types it: JSON lines out, exit 0."""
    bus = private_multicast_bus()
    mapping = write_mapping(tmp_path)
    catalog = tmp_path / "catalog.toml"
    target = f"{ROBOT_ADDR}:{JAUS_PORT}"
    with robot_namespace() as in_robot, (
        Proc("can-broker", "--can", bus, "--db", f"{tmp_path}/ecb.db", "--recovery", "0.2",
             prefix=in_robot)
    ), Proc("sub", "robot/max-speed", "--can", bus, "--json", "--count", "1", "--timeout", "120",
            prefix=in_robot) as wheels, Proc(
        "jaus", "--listen", f"0.0.0.0:{JAUS_PORT}", "--id", "1.1.1", "--map", str(mapping),
        "--can", bus, "--name", "rover", prefix=in_robot,
    ) as component:  # fmt: skip
        wheels.wait_for_line("subscribed to")
        component.wait_for_line("JAUS component 1.1.1")
        publish_fix(in_robot, bus, catalog, 48.4)

        def ocu(*args: str) -> list[dict[str, object]]:
            with Proc("jaus-ocu", *args) as proc:
                code, out = proc.finish(timeout=30)
            assert code == 0, "".join(proc.stderr_lines)
            return [json.loads(line) for line in out.splitlines()]

        (found,) = ocu("--broadcast", BROADCAST, "discover")
        assert found == {"id": "1.1.1", "address": target, "name": "rover", "type": 60001}
        (pose,) = ocu("--target", target, "query", "GlobalPose")
        assert pose["message"] == "ReportGlobalPose"
        assert pose["fields"]["latitude"] == pytest.approx(48.4, abs=1e-6)  # type: ignore[index]
        reports = ocu("--target", target, "watch", "GlobalPose", "--rate", "10", "--count", "3")
        assert [r["message"] for r in reports] == ["ReportGlobalPose"] * 3
        lines = ocu("--target", target, "send", "SetWrenchEffort", "propulsive_linear_x=25",
                    "--control")  # fmt: skip
        assert lines[0]["message"] == "ConfirmControl" and lines[-1] == {"sent": "SetWrenchEffort"}
        code, out = wheels.finish(timeout=60)
        assert code == 0 and json.loads(out)["data"] == struct.pack(">h", 50).hex()
        (status,) = ocu("--target", target, "query", "Status")
        assert status["fields"] == {"status": "STANDBY", "reserved": 0}  # released again
