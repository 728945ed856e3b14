"""Payloads and type hashes of ``ups ros2`` against what real ROS 2 makes: rclpy's
``serialize_message`` and the hashes ROS 2's build generates, from the PyPI wheels in an
environment of their own (tests/rclpy_reference.py). Float64, Int16, Bool, Twist and a ``.msg``
of the test's own (through a map, as ``ups ros2`` reads it).

rclpy leaves alignment padding uninitialised (whatever its buffer held) and ``ups ros2`` writes
zeros there: the bytes must be equal everywhere else. A byte that differs must therefore be
one that decoding ignores: the test checks that the reference decodes to the very values, and
that where the two differ ours is a zero.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from ups.ros2 import Codec, Types, load_map

from .rclpy_reference import CUSTOM_MSG, CUSTOM_NAME, reference

pytestmark = pytest.mark.timeout(600)  # the first run makes the rclpy environment

VALUES: dict[str, dict[str, Any]] = {
    "std_msgs/msg/Float64": {"data": -2.75},
    "std_msgs/msg/Int16": {"data": -1234},
    "std_msgs/msg/Bool": {"data": True},
    "geometry_msgs/msg/Twist": {
        "linear.x": 0.5, "linear.y": -1.25, "linear.z": 3.0,
        "angular.x": 0.0, "angular.y": 0.125, "angular.z": -0.75,
    },
}  # fmt: skip
CUSTOM_VALUES = {
    "header.stamp.sec": 1700000000, "header.stamp.nanosec": 250000000,
    "header.frame_id": "odom", "vector.x": 1.0, "vector.y": -2.0, "vector.z": 0.5,
}  # fmt: skip


@pytest.fixture(scope="module")
def ros() -> dict[str, Any]:
    return reference()


def encoded(types: Types, name: str, given: dict[str, Any]) -> tuple[Codec, list[Any], bytes]:
    codec = Codec(types.items(name))
    values = codec.zeros()
    paths = [v.path for v in codec.values]
    for path, value in given.items():
        values[paths.index(path)] = value
    return codec, values, codec.encode(values)


def same_but_padding(codec: Codec, values: list[Any], ours: bytes, theirs: bytes) -> None:
    assert len(ours) == len(theirs)
    assert codec.decode(theirs) == values
    differ = [i for i in range(len(ours)) if ours[i] != theirs[i]]
    assert all(ours[i] == 0 for i in differ)


@pytest.mark.parametrize("name", list(VALUES))
def test_payloads_and_type_hashes_are_rclpys(ros: dict[str, Any], name: str) -> None:
    types = Types("jazzy")
    codec, values, ours = encoded(types, name, VALUES[name])
    # every byte, but the padding rclpy leaves as it found it (a Bool's three after the value)
    same_but_padding(codec, values, ours, bytes.fromhex(ros["payloads"][name]))
    assert codec.decode(ours) == values
    assert types.type_hash(name) == ros["hashes"][name]


def test_a_msg_file_of_the_maps_own_hashes_and_serializes_as_ros_does(
    ros: dict[str, Any], tmp_path: Path
) -> None:
    (tmp_path / "StampedVector.msg").write_text(CUSTOM_MSG)
    (tmp_path / "catalog.toml").write_text(
        '[channel."v"]\nfields = [{ name = "x", type = "f64" }]\n'
    )
    (tmp_path / "map.toml").write_text(
        f'catalog = "catalog.toml"\ntypes = {{ "{CUSTOM_NAME}" = "StampedVector.msg" }}\n'
        f'[topic."/v"]\nchannel = "v"\ntype = "{CUSTOM_NAME}"\nfields."vector.x" = "x"\n'
    )
    topic = load_map(tmp_path / "map.toml").topics[0]
    assert topic.type_hash == ros["hashes"][CUSTOM_NAME]
    assert topic.type_hash != ros["hashes"]["geometry_msgs/msg/Vector3Stamped"]
    assert topic.key == f"0/v/ups_test::msg::dds_::StampedVector_/{ros['hashes'][CUSTOM_NAME]}"
    codec = topic.codec
    values = codec.zeros()
    for path, value in CUSTOM_VALUES.items():
        values[[v.path for v in codec.values].index(path)] = value
    theirs = bytes.fromhex(ros["payloads"]["CUSTOM"])
    same_but_padding(codec, values, codec.encode(values), theirs)


def test_a_mapped_event_is_the_message_rclpy_makes(ros: dict[str, Any], tmp_path: Path) -> None:
    """Through a map: a channel of six f32 (a twist) and one of an i16, as ``ups ros2``
    converts their events."""
    (tmp_path / "catalog.toml").write_text(
        '[channel."cmd"]\nfields = [' + ", ".join(
            f'{{ name = "{n}", type = "f32" }}' for n in ("lx", "ly", "lz", "ax", "ay", "az")
        ) + "]\n"
        '[channel."speed"]\nbyte_order = "big"\n'
        'fields = [{ name = "speed", type = "i16", scale = 0.01, unit = "m/s" }]\n'
    )  # fmt: skip
    (tmp_path / "map.toml").write_text(
        'catalog = "catalog.toml"\n'
        '[topic."/cmd_vel"]\nchannel = "cmd"\ntype = "geometry_msgs/msg/Twist"\n'
        'fields.linear = { x = "lx", y = "ly", z = "lz" }\n'
        'fields.angular = { x = "ax", y = "ay", z = "az" }\n'
        '[topic."/speed"]\nchannel = "speed"\ntype = "std_msgs/Int16"\nfields.data = '
        '{ field = "speed", scale = 0.01 }\n'
    )
    import struct

    twist, speed = load_map(tmp_path / "map.toml").topics
    event = struct.pack("<6f", 0.5, -1.25, 3.0, 0.0, 0.125, -0.75)
    assert twist.ros_payload(event, 0.0) == bytes.fromhex(
        ros["payloads"]["geometry_msgs/msg/Twist"]
    )
    assert twist.ups_payload(bytes.fromhex(ros["payloads"]["geometry_msgs/msg/Twist"])) == event
    assert speed.ros_payload(struct.pack(">h", -1234), 0.0) == bytes.fromhex(
        ros["payloads"]["std_msgs/msg/Int16"]
    )
    assert speed.ups_payload(bytes.fromhex(ros["payloads"]["std_msgs/msg/Int16"])) == b"\xfb\x2e"
