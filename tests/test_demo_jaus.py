"""``ups demo --jaus`` and ``ups jaus-ocu`` as a user types them, each a process, inside a
private network namespace (the demo's JAUS component takes UDP port 3794 on loopback, and
``discover`` broadcasts): the OCU finds the demo with no options, its Global Pose is plausible,
a 10 Hz Global Pose event keeps coming, paper 001's RA 3.3 pose query to the Global Pose
Sensor (component 38) is answered, a waypoint list is driven to its end, and a failing
``waypoints`` says why in one line that names no Python class; right after ``control
request``, the next runs are answered, or told in one line why not; every waypoint the robot
heads for is reported, in order; the demo's own operator stands aside while a JAUS operator
controls the robot."""

from __future__ import annotations

import json
import math
import re
import socket
import struct
import time
from collections.abc import Iterator
from datetime import UTC, datetime

import pytest

from .procs import Proc, private_multicast_bus

pytestmark = [pytest.mark.netns, pytest.mark.timeout(300)]

ORIGIN_LAT, ORIGIN_LON, ORIGIN_ALT = 48.4, 9.95, 480.0  # examples/navigation.py ORIGIN
CLASS_NAME = re.compile(r"\b[A-Z][a-z0-9]+[A-Z]\w*|Error\b|ups\.\w+|\('")  # CamelCase, repr


@pytest.fixture(scope="module")
def demo() -> Iterator[Proc]:
    private_multicast_bus()  # skips (or fails) outside a private network namespace
    with Proc("demo", "--jaus") as proc:
        proc.wait_for_line(r"Try, in another shell", timeout=120, stdout=True)
        yield proc


def ocu(*args: str, timeout: float = 60) -> list[dict[str, object]]:
    """``ups jaus-ocu ARGS``: its JSON lines; it must exit 0."""
    code, lines, errors = ocu_run(*args, timeout=timeout)
    assert code == 0, "".join(errors)
    return lines


def ocu_run(*args: str, timeout: float = 60) -> tuple[int, list[dict[str, object]], list[str]]:
    """``ups jaus-ocu ARGS``: its exit code, JSON lines and stderr lines."""
    with Proc("jaus-ocu", *args) as proc:
        code, out = proc.finish(timeout=timeout)
    return code, [json.loads(line) for line in out.splitlines()], proc.stderr_lines


def test_discover_finds_the_demo_with_no_options(demo: Proc) -> None:
    assert "  ups jaus-ocu discover\n" in demo.stdout_lines  # what the demo tells a user to try
    (found,) = ocu("discover")
    assert found == {"id": "1.1.1", "address": "127.0.0.1:3794", "name": "UPS demo robot",
                     "type": 60001}  # fmt: skip


def test_a_target_without_a_port_is_on_judps_port(demo: Proc) -> None:
    (status,) = ocu("--target", "127.0.0.1", "query", "Status")
    assert status["message"] == "ReportStatus" and status["from"] == "1.1.1"


def test_query_global_pose_is_a_plausible_fix(demo: Proc) -> None:
    (answer,) = ocu("query", "GlobalPose")
    assert answer["message"] == "ReportGlobalPose" and answer["from"] == "1.1.1"
    pose = answer["fields"]
    assert isinstance(pose, dict)
    # near the origin (the robot circles 2 m around it; 0.001 degrees is about 100 m)
    assert abs(pose["latitude"] - ORIGIN_LAT) < 1e-3 and abs(pose["longitude"] - ORIGIN_LON) < 1e-3
    assert pose["altitude"] == pytest.approx(ORIGIN_ALT, abs=0.01)
    assert -math.pi <= pose["yaw"] <= math.pi
    assert pose["position_rms"] == pytest.approx(0.71, abs=0.01)  # 0.5 m of noise per axis
    stamp = pose["timestamp"]  # when the fix arrived, UTC: now, give or take a busy machine
    assert isinstance(stamp, dict)
    now = datetime.now(UTC)
    assert 1 <= stamp["day"] <= 31
    of_day = stamp["hour"] * 3600 + stamp["minute"] * 60 + stamp["second"]
    assert (now.hour * 3600 + now.minute * 60 + now.second - of_day) % 86400 < 120


def test_a_10_hz_global_pose_event_keeps_coming(demo: Proc) -> None:
    reports = ocu("watch", "GlobalPose", "--rate", "10", "--count", "30")
    assert [r["message"] for r in reports] == ["ReportGlobalPose"] * 30
    fixes = {(r["fields"]["latitude"], r["fields"]["longitude"]) for r in reports}  # type: ignore[index]
    assert len(fixes) > 1  # each event the latest fix, and fixes move (the robot, the noise)


def test_paper_001s_ra33_pose_query_to_the_global_pose_sensor_is_answered(demo: Proc) -> None:
    """docs/jaus.md's second RA 3.3 worked example, byte for byte: "JAUS01.0", properties
    0x0206 (priority 6, version 2), Query Global Pose 0x2402, to instance 1 of component 38
    (the Global Pose Sensor) of node 1 of subsystem 1, from component 1 of node 1 of subsystem
    42, 2 bytes of data (presence vector 0x01FF), sequence number 3."""
    query = bytes.fromhex(
        "4a 41 55 53 30 31 2e 30 06 02 02 24 01 26 01 01 01 01 01 2a 02 00 03 00 ff 01"
    )
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(10)
        sock.sendto(query, ("127.0.0.1", 3794))
        data, _ = sock.recvfrom(65536)
    assert data[:8] == b"JAUS01.0"
    props, code = struct.unpack_from("<HH", data, 8)
    assert props >> 8 & 0x3F == 2 and code == 0x4402  # RA 3.2/3.3, Report Global Pose
    assert tuple(data[12:16]) == (1, 1, 1, 42)  # to instance 1, component 1, node 1, subsystem 42
    assert tuple(data[16:20]) == (1, 38, 1, 1)  # from the Global Pose Sensor, as asked
    size = struct.unpack_from("<H", data, 20)[0] & 0x0FFF
    assert len(data) == 24 + size
    presence, lat, lon = struct.unpack_from("<Hii", data, 24)
    assert presence & 0b11 == 0b11  # latitude, longitude; signed scaled integers (OpenJAUS)
    assert abs(lat * 180 / 4294967294 - ORIGIN_LAT) < 1e-3
    assert abs(lon * 360 / 4294967294 - ORIGIN_LON) < 1e-3


def test_a_waypoint_list_is_driven_to_its_end(demo: Proc) -> None:
    lines = ocu("waypoints", "2,0", "2,2", "0,2", "--speed", "0.3", timeout=240)
    assert (
        lines[0]["message"] == "ConfirmControl" and lines[1]["message"] == "ConfirmElementRequest"
    )
    active = [line["active"] for line in lines[2:]]
    assert active[-1] == 0 and set(active) <= {0, 1, 2, 3} and 3 in active  # to the tail
    heading = [line for line in demo.stdout_lines if line.startswith("navigator: heading for")]
    assert "navigator: heading for the waypoint x=0.00 m, y=2.00 m\n" in heading
    (pose,) = ocu("query", "LocalPose")
    fields = pose["fields"]
    assert isinstance(fields, dict)  # it drove there: within the robot's 1 m and a turn
    assert math.hypot(fields["x"] - 0, fields["y"] - 2) < 1.6
    (speed,) = ocu("query", "TravelSpeed")
    assert speed["fields"] == {"speed": pytest.approx(0.3, abs=0.01)}


@pytest.mark.parametrize(
    "args",
    [
        ("--to", "9.9.9", "--timeout", "1", "waypoints", "2,0"),  # nobody of that id answers
        ("--framing", "ra33", "waypoints", "2,0"),  # the list messages have no RA 3.3 form
        ("waypoints", "2,0", "5"),  # not X,Y
        ("waypoints", "2,0", "--tolerance", "500"),  # beyond JAUS's range
    ],
)
def test_a_failing_waypoints_says_why_in_one_line_naming_no_class(
    demo: Proc, args: tuple[str, ...]
) -> None:
    with Proc("jaus-ocu", "--target", "127.0.0.1:3794", *args) as proc:
        code, _ = proc.finish(timeout=60)
    assert code == 2, proc.stderr_lines
    (line,) = proc.stderr_lines
    assert line.startswith("ups jaus-ocu: ") and not CLASS_NAME.search(line), line


def test_a_second_jaus_demo_on_the_same_port_says_why_in_one_line(demo: Proc) -> None:
    with Proc("demo", "--jaus") as second:
        code, _ = second.finish(timeout=120)
    errors = [line for line in second.stderr_lines if " WARNING: " not in line]
    assert code == 2 and errors == [
        "ups demo: the JAUS component cannot listen on 127.0.0.1:3794 (UDP): Address already in "
        "use; try --jaus HOST:PORT\n"
    ]


HELD_BY_AN_EARLIER_RUN = (
    "200.1.1 (this OCU's --id) controls it from another address: the control an earlier run "
    "took, which lapses 5 s after that run's last message"
)


def test_right_after_control_request_the_next_run_is_answered_or_told_why(demo: Proc) -> None:
    """Issue 39: after ``control request``, every ``ups jaus-ocu`` run got no answer at all
    until the control lapsed (the component held the id's control at the first run's port and
    dropped everything else from that id). Now queries are answered, and what is refused says
    so in one line naming the holder; each within the OCU's own 2 s timeout."""
    (granted,) = ocu("control", "request")
    assert granted["fields"] == {"response": "CONTROL_ACCEPTED"}
    (found,) = ocu("discover")
    assert found["id"] == "1.1.1"
    (status,) = ocu("query", "Status")
    assert status["fields"] == {"status": "STANDBY", "reserved": 0}
    (control,) = ocu("control", "query")
    assert control["fields"] == {"subsystem": 200, "node": 1, "component": 1, "authority": 10}
    for args, answer, why in (
        (("send", "SetWrenchEffort", "propulsive_linear_x=20", "--control"),
         {"response": "NOT_AVAILABLE"},
         f"control of 1.1.1 is not available: {HELD_BY_AN_EARLIER_RUN}"),
        (("send", "SetWrenchEffort", "propulsive_linear_x=20"), None,
         "Set Wrench Effort went without control, and 1.1.1 carries it out only from the OCU "
         f"that controls it: {HELD_BY_AN_EARLIER_RUN}; give --control"),
        (("waypoints", "2,0"), {"response": "NOT_AVAILABLE"},
         f"control of 1.1.1 is not available: {HELD_BY_AN_EARLIER_RUN}"),
        (("control", "release"), {"response": "NOT_AVAILABLE"},
         f"nothing to release: this run does not control 1.1.1; {HELD_BY_AN_EARLIER_RUN}"),
        (("watch", "GlobalPose", "--count", "1"), None,
         "1.1.1 refused the event (CONNECTION_REFUSED): 200.1.1 controls this component from "
         "another address"),
    ):  # fmt: skip
        code, lines, errors = ocu_run(*args)
        assert (code, errors) == (1, [f"ups jaus-ocu: {why}\n"]), args
        if answer is not None:
            assert lines[0]["fields"] == answer
    wait_until_nobody_controls()


def test_a_refusal_names_the_other_controller_or_nobody(demo: Proc) -> None:
    """The reason a refusal gives is the component's own report: nobody controls it (a
    command sent without control), or another OCU does, at an authority a request must
    exceed."""
    wrench = ("send", "SetWrenchEffort", "propulsive_linear_x=20")
    code, _, errors = ocu_run(*wrench)
    assert (code, errors) == (1, [
        "ups jaus-ocu: Set Wrench Effort went without control, and 1.1.1 carries it out only "
        "from the OCU that controls it: nobody controls it; give --control\n"])  # fmt: skip
    (granted,) = ocu("--id", "42.1.2", "control", "request", "--authority", "50")
    assert granted["fields"] == {"response": "CONTROL_ACCEPTED"}
    code, _, errors = ocu_run(*wrench, "--control")
    assert (code, errors) == (1, [
        "ups jaus-ocu: control of 1.1.1 is not available: 42.1.2 controls it at authority 50, "
        "and only a higher authority takes control from it\n"])  # fmt: skip
    wait_until_nobody_controls()


def wait_until_nobody_controls(within: float = 60) -> None:
    """Until the component reports no controller (a control left by a test lapses after 5 s
    of silence), so that the next test may take control."""
    deadline = time.monotonic() + within
    while ocu("control", "query")[0]["fields"] != NOBODY:
        assert time.monotonic() < deadline, "the control never lapsed"


NOBODY = {"subsystem": 0, "node": 0, "component": 0, "authority": 0}


def test_every_waypoint_the_robot_heads_for_is_reported_in_order(demo: Proc) -> None:
    """Issue 39: ``waypoints 1,0 1,1`` reported active 1 then 0, never 2, though the robot
    headed for (1, 1): the OCU asked every 0.5 s and the robot got within the tolerance of
    both sooner. Within 100 m each waypoint is reached at the next pose, far quicker than the
    3 s between questions here: every one is still reported, in order, then 0."""
    lines = ocu("waypoints", "1,0", "1,1", "--tolerance", "100", "--poll", "3")
    assert [line.get("active") for line in lines[2:]] == [1, 2, 0]
    demo.wait_for_line(r"navigator: heading for the waypoint x=1\.00 m, y=1\.00 m", stdout=True)


def test_the_demos_operator_stands_aside_while_a_jaus_operator_controls(demo: Proc) -> None:
    """Issue 39: the operator station on TCP/IP capped robot/max-speed at 30 cm/s every 0.5 s
    while the robot went faster, so an OCU's Set Wrench Effort (20 %: 40 cm/s) was undone at
    once. While the OCU holds control, 40 speed readings in a row are 40 cm/s; once it lets
    go, the station caps the robot again, and says so, as the demo's text does."""
    said = "".join(demo.stdout_lines[: printed(demo, r"^cm/s again\.$", 0)])  # the demo's text
    command = "ups jaus-ocu send SetWrenchEffort propulsive_linear_x=20 --control --hold 10"
    assert f"  {command}\n" in said
    assert "While a JAUS operator controls the\nrobot, the operator station on TCP/IP stands " \
        "aside; when none does, it caps the speed at 30\ncm/s again." in said  # fmt: skip
    start = len(demo.stdout_lines)
    with Proc("jaus-ocu", "send", "SetWrenchEffort", "propulsive_linear_x=20", "--control",
              "--hold", "120") as holder:  # fmt: skip
        holder.wait_for_line('"sent"', 60, stdout=True)
        printed(demo, r"operator \(TCP\): JAUS operator 200\.1\.1 controls the robot; "
                r"leaving robot/max-speed to it", start)  # fmt: skip
        printed(demo, r"wheel-encoder: speed limit 40 cm/s", start)  # in either order
        speeds = ocu("--id", "201.1.1", "watch", "VelocityState", "--change", "--count", "40")
        velocity = [s["fields"]["velocity_x"] for s in speeds]  # type: ignore[index]
        assert velocity == [pytest.approx(0.4, abs=0.005)] * 40
        start = len(demo.stdout_lines)
        holder.interrupt()  # Ctrl-C: it lets go
        assert holder.finish(timeout=60)[0] == 130
    printed(demo, r"operator \(TCP\): no JAUS operator controls the robot; I cap it at "
            r"30 cm/s again", start)  # fmt: skip
    printed(demo, r"wheel-encoder: speed limit 30 cm/s", start)


def printed(proc: Proc, pattern: str, start: int, timeout: float = 60) -> int:
    """Wait for a stdout line of ``proc`` matching ``pattern`` among those from index
    ``start`` on; the index after it."""
    regex, deadline, at = re.compile(pattern), time.monotonic() + timeout, start
    while True:
        lines = proc.wait_for_stdout(at + 1, timeout=max(0.0, deadline - time.monotonic()))
        for i in range(at, len(lines)):
            if regex.search(lines[i]):
                return i + 1
        at = len(lines)
