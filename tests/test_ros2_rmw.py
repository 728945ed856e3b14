"""rmw_zenoh's conventions (ros2/_rmw.py) against the examples of its docs/design.md at the
pinned commit, byte for byte, and the attachment and GID as the document and the code it names
describe them."""

from __future__ import annotations

import struct

import pytest
import xxhash

from ups.ros2 import (
    RMW_ZENOH_COMMIT,
    Qos,
    attachment,
    dds_type_name,
    entity_token,
    gid,
    node_token,
    read_attachment,
    topic_key,
)
from ups.ros2._rmw import PROFILES

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


def test_the_commit_is_pinned() -> None:
    assert RMW_ZENOH_COMMIT == "99a6a2bd10b949052f4f12c5854825dc005e95a5"


def test_the_topic_keys_of_design_md() -> None:
    assert topic_key(0, "chatter", "std_msgs/msg/String", STRING_HASH) == (
        "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH
    )
    assert topic_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == (
        "0/robot1/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH
    )
    assert topic_key(2, "add_two_ints", "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH) == (
        "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/" + ADD_TWO_INTS_HASH
    )
    assert topic_key(7, "/robot/speed/", "std_msgs/msg/Int16", "TypeHashNotSupported") == (
        "7/robot/speed/std_msgs::msg::dds_::Int16_/TypeHashNotSupported"
    )


def test_the_liveliness_tokens_of_design_md() -> None:
    listener = "aac3178e146ba6f1fc6e6a4085e77f21"
    assert node_token(2, listener, 0, "/", "listener") == (
        f"@ros2_lv/2/{listener}/0/0/NN/%/%/listener"
    )
    assert entity_token(2, listener, 0, 10, "MS", "/", "listener", "/chatter",
                        "std_msgs/msg/String", STRING_HASH, Qos(depth=10)) == (
        f"@ros2_lv/2/{listener}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,"
    )  # fmt: skip
    talker = "8b20917502ee955ac4476e0266340d5c"
    assert entity_token(2, talker, 0, 10, "MP", "/", "talker", "/chatter",
                        "std_msgs/msg/String", STRING_HASH, Qos(depth=7)) == (
        f"@ros2_lv/2/{talker}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,"
    )  # fmt: skip
    server = "f9980ee0495eaafb3e38f0d19e2eae12"
    assert entity_token(2, server, 0, 10, "SS", "/", "add_two_ints_server", "/add_two_ints",
                        "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH,
                        Qos(depth=10)) == (
        f"@ros2_lv/2/{server}/0/10/SS/%/%/add_two_ints_server/%add_two_ints/"
        f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,"
    )  # fmt: skip


@pytest.mark.parametrize(
    ("qos", "chunk"),
    [
        (Qos(), "::,:,:,:,,"),  # rmw_zenoh's own default: reliable, volatile, keep last 42
        (PROFILES["default"], "::,10:,:,:,,"),
        (PROFILES["sensor_data"], "2::,5:,:,:,,"),
        (Qos(reliability=2, history=2, depth=1), "2::2,1:,:,:,,"),
    ],
)
def test_the_qos_chunk_leaves_out_rmw_zenohs_defaults(qos: Qos, chunk: str) -> None:
    assert qos.chunk() == chunk


def test_a_namespace_and_a_node_name_are_mangled() -> None:
    token = node_token(0, "ab", 3, "/robot/arm", "ups_bridge")
    assert token == "@ros2_lv/0/ab/3/3/NN/%/%robot%arm/ups_bridge"
    assert dds_type_name("geometry_msgs/msg/Twist") == "geometry_msgs::msg::dds_::Twist_"


def test_the_gid_is_xxh3_128_of_the_token_low_half_first() -> None:
    token = f"@ros2_lv/0/{'1' * 32}/0/1/MP/%/%/ups/%t/std_msgs::msg::dds_::Int16_/x/::,10:,:,:,,"
    digest = xxhash.xxh3_128(token.encode()).intdigest()
    low, high = digest & (1 << 64) - 1, digest >> 64
    assert gid(token) == struct.pack("<QQ", low, high)
    assert gid(token) != gid(token + "x")
    # the canonical (big-endian) digest is the same 16 bytes, halves and bytes reversed
    assert gid(token) == xxhash.xxh3_128(token.encode()).digest()[::-1]


def test_the_attachment_is_33_bytes_sequence_time_16_gid() -> None:
    who = bytes(range(16))
    data = attachment(1, 1_700_000_000_123_456_789, who)
    assert data == (
        (1).to_bytes(8, "little") + (1_700_000_000_123_456_789).to_bytes(8, "little")
        + b"\x10" + who
    )  # fmt: skip
    found = read_attachment(data)
    assert found is not None
    assert (found.sequence, found.source_time_ns, found.gid) == (1, 1_700_000_000_123_456_789, who)
    assert read_attachment(data[:-1]) is None
    assert read_attachment(None) is None
    assert read_attachment(data[:16] + b"\x0f" + who) is None
