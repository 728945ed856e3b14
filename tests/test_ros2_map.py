"""The map of ``ups ros2``: ``ups ros2 check`` (exit 2 naming the line of an unknown type,
field, channel or direction, or of a type mismatch), the demo robot's map, and the conversions
the map compiles: exact where the types allow, never clipped."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest

from ups.ros2 import Unrepresentable, load_map
from ups.ros2._admit import DEFAULT_BURST, DEFAULT_RATE
from upscli import main

from .procs import ROOT, Proc

CATALOG = """
[channel."robot/speed"]
byte_order = "big"
fields = [{ name = "speed", type = "i16", unit = "cm/s" }]

[channel."robot/label"]
fields = [{ name = "level", type = "u8" }, { name = "text", type = "str" }]
"""

GOOD = """\
catalog = "catalog.toml"
node = "bridge"

[topic."/robot/speed"]
channel = "robot/speed"
type = "std_msgs/msg/Float64"
direction = "both"
fields.data = { field = "speed", scale = 100.0 }

[topic."/robot/label"]
channel = "robot/label"
type = "std_msgs/msg/String"
direction = "from_ros"
fields.data = "text"
ups_constants = { level = 3 }
"""


def write(tmp_path: Path, text: str) -> Path:
    (tmp_path / "catalog.toml").write_text(CATALOG)
    path = tmp_path / "map.toml"
    path.write_text(text)
    return path


def check(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["ros2", "check", str(path)])
    out = capsys.readouterr()
    return code, out.out + out.err


def test_a_good_map_is_listed_with_its_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, text = check(write(tmp_path, GOOD), capsys)
    assert code == 0, text
    assert "/robot/speed (std_msgs/msg/Float64, both) on robot/speed: data<->speed" in text
    assert "key 0/robot/speed/std_msgs::msg::dds_::Float64_/RIHS01_705ba9c3" in text


def test_a_topic_from_ros_takes_its_rate_bound_or_the_default(tmp_path: Path) -> None:
    bounded = GOOD.replace('direction = "from_ros"', 'direction = "from_ros"\nmax_rate = 2.5\n'
                           "burst = 1")  # fmt: skip
    speed, label = load_map(write(tmp_path, bounded)).topics
    assert (speed.max_rate, speed.burst) == (DEFAULT_RATE, DEFAULT_BURST) == (100.0, 20)
    assert (label.max_rate, label.burst) == (2.5, 1)
    assert label.describe()["max_rate"] == 2.5 and label.describe()["burst"] == 1


@pytest.mark.parametrize(
    ("change", "line", "says"),
    [
        (
            ('type = "std_msgs/msg/Float64"', 'type = "std_msgs/msg/Float65"'),
            6,
            "unknown type std_msgs/msg/Float65",
        ),
        (
            ("fields.data = { field", "fields.date = { field"),
            8,
            "unknown field: std_msgs/msg/Float64 has no value 'date'",
        ),
        (
            ('field = "speed"', 'field = "sped"'),
            8,
            "unknown field: channel robot/speed has no field 'sped'",
        ),
        (('channel = "robot/speed"', 'channel = "robot/sped"'), 5, "unknown channel robot/sped"),
        (('direction = "both"', 'direction = "to_ups"'), 7, "unknown direction 'to_ups'"),
        (
            ('fields.data = "text"', 'fields.data = "level"'),
            14,
            "type mismatch: std_msgs/msg/String data (string) and robot/label level (u8)",
        ),
        (
            ("ups_constants = { level = 3 }", 'ups_constants = { level = "high" }'),
            15,
            "type mismatch: level is a number (uint8), not 'high'",
        ),
        (
            ("ups_constants = { level = 3 }", ""),
            10,
            "'level' is neither mapped nor in ups_constants",
        ),
        (
            ("ups_constants = { level = 3 }", "ups_constants = { level = 300 }"),
            10,
            "300 is out of range 0..255",
        ),
        (  # values ups ros2 cannot run with (issue 41)
            ("ups_constants = { level = 3 }", "ups_constants = { level = nan }"),
            15,
            "type mismatch: level is a number (uint8), not nan",
        ),
        (
            ('direction = "from_ros"', 'direction = "from_ros"\nqos = { depth = 2147483648 }'),
            14,
            "qos: depth is a number of samples from 1 to 10000",
        ),
        *(  # the rate bound from ROS: finite, above 0, at most 10000/s (issue 41)
            (
                ('direction = "from_ros"', f'direction = "from_ros"\nmax_rate = {rate}'),
                14,
                f"max_rate is samples a second, above 0 and at most 10000, not {said}",
            )
            for rate, said in (
                ("inf", "inf"),
                ("nan", "nan"),
                ("0", "0"),
                ("-5", "-5"),
                ("1e9", "1000000000.0"),
                ('"fast"', "'fast'"),
            )
        ),
        *(
            (
                ('direction = "from_ros"', f'direction = "from_ros"\nburst = {burst}'),
                14,
                f"burst is a number of samples from 1 to 10000, not {said}",
            )
            for burst, said in (
                ("0", "0"),
                ("2.5", "2.5"),
                ("100000", "100000"),
                ("true", "True"),
            )
        ),
        (
            ('direction = "both"', 'direction = "to_ros"\nmax_rate = 10'),
            8,
            "max_rate bounds what comes from ROS: this topic only goes to ROS",
        ),
    ],
)
def test_a_bad_map_exits_2_naming_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], change: tuple[str, str], line: int,
    says: str,
) -> None:  # fmt: skip
    assert change[0] in GOOD
    path = write(tmp_path, GOOD.replace(*change))
    code, text = check(path, capsys)
    assert code == 2
    assert text.startswith(f"ups ros2: {path}:{line}: ")
    assert says in text
    assert len(text.strip().splitlines()) == 1


def test_a_message_is_not_a_value_and_unknown_keys_are_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    twist = GOOD.replace('type = "std_msgs/msg/Float64"', 'type = "geometry_msgs/msg/Twist"')
    code, text = check(write(tmp_path, twist.replace("fields.data", "fields.linear")), capsys)
    assert code == 2 and ":8: " in text and "a message, not a value" in text
    code, text = check(write(tmp_path, GOOD.replace('node = "bridge"', 'nodes = "b"')), capsys)
    assert code == 2 and ":2: unknown key 'nodes'" in text
    code, text = check(write(tmp_path, GOOD + 'qos = "fast"\n'), capsys)
    assert code == 2 and ":16: " in text and "'fast' is not a profile" in text


def test_the_demo_robots_map_checks_as_a_process() -> None:
    with Proc("ros2", "check", str(ROOT / "examples" / "robot.ros2.toml")) as proc:
        code, out = proc.finish()
    assert code == 0, "".join(proc.stderr_lines)
    topics = [line.split()[0] for line in out.splitlines() if not line.startswith(" ")]
    assert topics == ["/robot/speed", "/robot/sonar", "/robot/brake", "/robot/max_speed",
                      "/robot/local_pose", "/robot/fix", "/robot/waypoint"]  # fmt: skip
    bridge = load_map(ROOT / "examples" / "robot.ros2.toml")
    pose = next(t for t in bridge.topics if t.topic == "/robot/local_pose")
    # x 2 m north, y 1 m east, yaw 0 (north): ROS x 1 (east), y 2 (north), theta pi/2
    x, y, theta = struct.unpack_from("<3d", pose.ros_payload(struct.pack(">iih", 2000, 1000, 0),
                                                              0.0), 4)  # fmt: skip
    assert (x, y) == (1.0, 2.0) and theta == pytest.approx(math.pi / 2)


def test_values_the_other_side_cannot_hold_are_refused_never_clipped(tmp_path: Path) -> None:
    speed, label = load_map(write(tmp_path, GOOD)).topics
    f64 = struct.Struct("<d")
    assert speed.ups_payload(b"\x00\x01\x00\x00" + f64.pack(1.5)) == struct.pack(">h", 150)
    assert speed.ups_payload(b"\x00\x01\x00\x00" + f64.pack(-327.68)) == struct.pack(">h", -32768)
    for bad in (327.68, -327.69, math.nan, math.inf):
        with pytest.raises(Unrepresentable):
            speed.ups_payload(b"\x00\x01\x00\x00" + f64.pack(bad))
    assert speed.ros_payload(struct.pack(">h", -5), 0.0) == b"\x00\x01\x00\x00" + f64.pack(-0.05)
    assert label.ups_payload(b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00") == b"\x03hi"


def test_integers_stay_exact_and_out_of_range_is_refused(tmp_path: Path) -> None:
    (tmp_path / "catalog.toml").write_text(
        '[channel."big"]\nfields = [{ name = "n", type = "u64" }, { name = "s", type = "i32" }]\n'
    )
    (tmp_path / "map.toml").write_text(
        'catalog = "catalog.toml"\n[topic."/n"]\nchannel = "big"\ntype = "std_msgs/UInt64"\n'
        'direction = "both"\nfields.data = "n"\nups_constants = { s = -1 }\n'
        '[topic."/s"]\nchannel = "big"\ntype = "std_msgs/Int16"\nfields.data = "s"\n'
    )
    n, s = load_map(tmp_path / "map.toml").topics
    top = (1 << 64) - 1
    event = struct.pack("<Qi", top, -1)
    assert n.ros_payload(event, 0.0) == b"\x00\x01\x00\x00" + struct.pack("<Q", top)
    assert n.ups_payload(b"\x00\x01\x00\x00" + struct.pack("<Q", top)) == event
    assert s.ros_payload(struct.pack("<Qi", 0, -32768), 0.0)[4:6] == struct.pack("<h", -32768)
    with pytest.raises(Unrepresentable, match=r"out of range -32768\.\.32767"):
        s.ros_payload(struct.pack("<Qi", 0, 40000), 0.0)


def test_humble_has_no_type_hashes(tmp_path: Path) -> None:
    path = write(tmp_path, GOOD.replace('node = "bridge"', 'node = "bridge"\ndistro = "humble"'))
    speed = load_map(path, domain=5).topics[0]
    assert speed.key == "5/robot/speed/std_msgs::msg::dds_::Float64_/TypeHashNotSupported"
