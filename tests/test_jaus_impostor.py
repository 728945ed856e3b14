"""Control of a ``ups jaus`` process belongs to a JAUS id *and* the UDP address it came from,
and the mapping caps the authority granted per address range: real processes (a TCP-ECB, the
component, a ``ups sub`` standing for the wheels) and real UDP clients on loopback, written
here from the public definitions (AS5669A, AS5710A), not with the project's codec.

The proof that a command was not carried out is in the order: the wheels take one event,
and it must be the one the rightful controller sent after the intruder's."""

from __future__ import annotations

import ast
import contextlib
import json
import socket
import struct
from collections.abc import Iterator
from pathlib import Path

from .procs import ROOT, Proc, start_tcp_broker

ROBOT = (7, 1, 1)
OPERATOR = (200, 1, 1)
REQUEST_CONTROL, CONFIRM_CONTROL, RESUME, SET_WRENCH_EFFORT = 0x000D, 0x000F, 0x0004, 0x0405
RELEASE_CONTROL, REJECT_CONTROL = 0x000E, 0x0010
QUERY_CONTROL, REPORT_CONTROL, QUERY_STATUS, REPORT_STATUS = 0x200D, 0x400D, 0x2002, 0x4002
QUERY_TIMEOUT, REPORT_TIMEOUT = 0x2003, 0x4003
CREATE_EVENT, REJECT_EVENT_REQUEST = 0x01F0, 0x01F4
READY, STANDBY = 1, 2
CONNECTION_REFUSED = 3
NOT_AVAILABLE, INSUFFICIENT_AUTHORITY = 1, 2

MAPPING = """
catalog = "{catalog}"
{authority}
[message.SetWrenchEffort]
channel = "robot/max-speed"
fields.propulsive_linear_x = {{ field = "limit", scale = 2.0 }}
"""


def jaus_id(subsystem: int, node: int, component: int) -> bytes:
    return struct.pack("<I", subsystem << 16 | node << 8 | component)


class Ocu:
    """A JUDP client: version 2, then one message: type/HC 0, data size u16 (from that byte
    to the sequence number), properties (priority standard), destination, source, code,
    payload, sequence number; little-endian."""

    def __init__(self, robot: tuple[str, int], me: tuple[int, int, int], host: str) -> None:
        self.robot, self.me, self.seq = robot, me, 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.sock.settimeout(10)

    def send(self, code: int, payload: bytes = b"") -> None:
        body = jaus_id(*ROBOT) + jaus_id(*self.me) + struct.pack("<H", code) + payload
        self.seq += 1
        datagram = bytes((2, 0)) + struct.pack("<HB", 1 + 2 + 1 + len(body) + 2, 0x01) + body
        self.sock.sendto(datagram + struct.pack("<H", self.seq), self.robot)

    def ask(self, code: int, payload: bytes, answer: int) -> bytes:
        """Send, then the payload of the answer with code ``answer`` (a timeout fails)."""
        self.send(code, payload)
        data = self.sock.recv(65536)
        size = struct.unpack_from("<H", data, 2)[0]
        assert struct.unpack_from("<H", data, 13)[0] == answer
        return data[15 : 1 + size - 2]

    def close(self) -> None:
        self.sock.close()


def effort(percent: float) -> bytes:
    """Set Wrench Effort, propulsive linear x only (presence vector bit 0), u16 scaled over
    [-100, 100] %."""
    return struct.pack("<HH", 0x0001, round((percent + 100) / 200 * 0xFFFF))


@contextlib.contextmanager
def robot(tmp_path: Path, authority: str = "") -> Iterator[tuple[tuple[str, int], Proc, Proc]]:
    """A TCP-ECB, the wheels (``ups sub robot/max-speed --count 1``) and ``ups jaus`` on
    127.0.0.1; yields the component's UDP address, the wheels and the component."""
    mapping = tmp_path / "robot.jaus.toml"
    catalog = ROOT / "examples" / "robots.toml"
    mapping.write_text(MAPPING.format(catalog=catalog, authority=authority))
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc(
        "sub", "robot/max-speed", "--broker", address, "--json",
        "--count", "1", "--timeout", "60",
    ) as wheels, Proc(
        "jaus", "--listen", "127.0.0.1:0", "--id", "7.1.1", "--map", str(mapping),
        "--broker", address,
    ) as component:  # fmt: skip
        wheels.wait_for_line("subscribed to")
        line = component.wait_for_line(r"JAUS component 7\.1\.1 on 127\.0\.0\.1:\d+")
        port = int(line.split("127.0.0.1:")[1].split()[0])
        yield ("127.0.0.1", port), wheels, component


def the_wheels_got(wheels: Proc) -> int:
    """The speed limit (cm/s) of the one event the wheels took."""
    code, out = wheels.finish(timeout=60)
    assert code == 0
    return int(struct.unpack(">h", bytes.fromhex(json.loads(out)["data"]))[0])


def stats_at_stop(component: Proc) -> dict[str, int]:
    """The counters ``ups jaus`` logs when it stops (``JAUS component stopping: {...}``)."""
    assert component.stop() == 0
    (line,) = [ln for ln in component.stderr_lines if "JAUS component stopping:" in ln]
    stats: dict[str, int] = ast.literal_eval(line.split("JAUS component stopping: ")[1])
    return stats


def test_the_controllers_id_from_another_port_is_refused_and_counted(tmp_path: Path) -> None:
    """The reported attack: a second client uses the controlling OCU's JAUS id from another
    UDP port. Its Set Wrench Effort was published on robot/max-speed, and its Request Control
    was taken for the holder's asking again (moving the holder's answers to it)."""
    with robot(tmp_path) as (address, wheels, component):
        operator = Ocu(address, OPERATOR, "127.0.0.1")
        impostor = Ocu(address, OPERATOR, "127.0.0.1")  # the same id, another port
        assert operator.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([0])
        operator.send(RESUME)
        assert operator.ask(QUERY_STATUS, b"", REPORT_STATUS)[0] == READY  # Resume handled
        impostor.send(SET_WRENCH_EFFORT, effort(90))  # 180 cm/s, if obeyed
        assert impostor.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([NOT_AVAILABLE])
        component.wait_for_line(r"from another address")  # logged
        operator.send(SET_WRENCH_EFFORT, effort(10))  # 20 cm/s: the operator still drives
        assert the_wheels_got(wheels) == 20
        # the operator still holds control, with the authority it asked for
        body = operator.ask(QUERY_CONTROL, b"", REPORT_CONTROL)
        assert body == struct.pack("<HBBB", *OPERATOR, 10)
        operator.close()
        impostor.close()
        stats = stats_at_stop(component)
    assert stats["refused_other_address"] == 2 and stats["commands"] == 1
    assert stats["control_granted"] == 1


def test_the_controllers_id_from_another_port_is_answered_its_queries_and_told_the_rest(
    tmp_path: Path,
) -> None:
    """Issue 39: a second run of an OCU with the controller's id (``ups jaus-ocu`` right after
    ``control request``) got no answer at all until the control lapsed. Its queries are
    answered, at its own port, and what it may not do is refused aloud: Release Control with
    Not Available, Create Event with Reject Event Request (connection refused, saying why).
    The controller keeps control, and its answers keep coming to it alone."""
    with robot(tmp_path) as (address, wheels, component):
        operator = Ocu(address, OPERATOR, "127.0.0.1")
        second = Ocu(address, OPERATOR, "127.0.0.1")  # the same id, another port
        assert operator.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([0])
        body = second.ask(QUERY_CONTROL, b"", REPORT_CONTROL)
        assert body == struct.pack("<HBBB", *OPERATOR, 10)
        assert second.ask(QUERY_STATUS, b"", REPORT_STATUS)[0] == STANDBY
        assert second.ask(QUERY_TIMEOUT, b"", REPORT_TIMEOUT) == bytes([5])  # seconds
        assert second.ask(RELEASE_CONTROL, b"", REJECT_CONTROL) == bytes([NOT_AVAILABLE])
        # Create Event: request 1, every change, rate 0, the query (count u32, then its code)
        create = struct.pack("<BBHIH", 1, 1, 0, 2, QUERY_STATUS)
        refused = second.ask(CREATE_EVENT, create, REJECT_EVENT_REQUEST)
        assert refused[:3] == bytes([0b11, 1, CONNECTION_REFUSED])  # with a code and a text
        assert refused[3:].rstrip(b"\0") == b"200.1.1 controls this component from another address"
        # the operator still controls: it resumes and drives, its answers come to it
        operator.send(RESUME)
        assert operator.ask(QUERY_STATUS, b"", REPORT_STATUS)[0] == READY
        operator.send(SET_WRENCH_EFFORT, effort(10))
        assert the_wheels_got(wheels) == 20
        operator.close()
        second.close()
        stats = stats_at_stop(component)
    assert stats["refused_other_address"] == 2  # the Release Control and the Create Event
    assert stats["control_granted"] == 1 and stats["commands"] == 1


AUTHORITY = """
[authority]                 # the most authority granted per source address range
"127.0.0.1/32" = 255
"127.0.0.2/32" = 5
"""


def test_the_mapping_caps_the_authority_an_address_range_is_granted(tmp_path: Path) -> None:
    """A higher authority takes control (AS5710A): an intruder asking 255 from 127.0.0.2
    displaced the operator. Capped at 5 for its range, it is refused; an address in no range
    is granted no control at all."""
    with robot(tmp_path, AUTHORITY) as (address, wheels, component):
        operator = Ocu(address, OPERATOR, "127.0.0.1")
        intruder = Ocu(address, (66, 1, 1), "127.0.0.2")
        outsider = Ocu(address, (67, 1, 1), "127.0.0.3")
        assert operator.ask(REQUEST_CONTROL, bytes([10]), CONFIRM_CONTROL) == bytes([0])
        operator.send(RESUME)
        assert operator.ask(QUERY_STATUS, b"", REPORT_STATUS)[0] == READY
        assert intruder.ask(REQUEST_CONTROL, bytes([255]), CONFIRM_CONTROL) == bytes(
            [NOT_AVAILABLE]
        )  # 5 is not above the operator's 10
        intruder.send(SET_WRENCH_EFFORT, effort(90))  # refused: it has no control
        # handled by now (one socket's datagrams are served in order): the operator holds
        body = intruder.ask(QUERY_CONTROL, b"", REPORT_CONTROL)
        assert body == struct.pack("<HBBB", *OPERATOR, 10)
        assert outsider.ask(REQUEST_CONTROL, bytes([255]), CONFIRM_CONTROL) == bytes(
            [INSUFFICIENT_AUTHORITY]
        )
        component.wait_for_line(r"authority 255 .*capped")  # logged
        operator.send(SET_WRENCH_EFFORT, effort(10))
        assert the_wheels_got(wheels) == 20
        # once the operator lets go, the intruder may take control, at its cap
        assert operator.ask(RELEASE_CONTROL, b"", REJECT_CONTROL) == bytes([0])
        assert intruder.ask(REQUEST_CONTROL, bytes([255]), CONFIRM_CONTROL) == bytes([0])
        assert intruder.ask(QUERY_CONTROL, b"", REPORT_CONTROL) == struct.pack("<HBBB", 66, 1, 1, 5)
        for ocu in (operator, intruder, outsider):
            ocu.close()
        stats = stats_at_stop(component)
    assert stats["authority_capped"] == 3 and stats["refused_without_control"] == 1
