"""docs/ros2.md's worked example, computed with the bridge's own code from the demo robot's
map: every key, token, GID, payload and attachment it shows."""

from __future__ import annotations

from ups.ros2 import RMW_ZENOH_COMMIT, attachment, entity_token, gid, load_map, node_token
from ups.ros2._rmw import PUBLISHER, SUBSCRIPTION

from .procs import ROOT

DOC = (ROOT / "docs" / "ros2.md").read_text()
ZID = "5c1e0f7a9b3d42e8a1f06c2d7e9b8a34"


def spaced(data: bytes) -> str:
    return data.hex(" ")


def test_the_worked_example_is_what_the_bridge_makes() -> None:
    bridge = load_map(ROOT / "examples" / "robot.ros2.toml")
    index = next(i for i, t in enumerate(bridge.topics) if t.topic == "/robot/max_speed")
    topic = bridge.topics[index]
    assert index + 1 == 4  # "the map's fourth: publisher 7, subscription 8"
    publisher, subscription = 2 * (index + 1) - 1, 2 * (index + 1)
    assert f"\n{topic.key}\n" in DOC
    assert f"\n{node_token(0, ZID, 0, '/', bridge.node)}\n" in DOC
    tokens = [
        entity_token(0, ZID, 0, entity, kind, "/", bridge.node, topic.topic, topic.type,
                     topic.type_hash, topic.qos)
        for entity, kind in ((publisher, PUBLISHER), (subscription, SUBSCRIPTION))
    ]  # fmt: skip
    assert all(f"\n{token}\n" in DOC for token in tokens)
    who = gid(tokens[0])
    assert f"XXH3-128 of its token: `{spaced(who)}`" in DOC
    payload = topic.ros_payload(bytes.fromhex("0032"), 1_700_000_000.0)
    assert payload == bytes.fromhex("00010000" + "000000000000e03f")
    assert f"| `{spaced(payload[:4])}` | encapsulation" in DOC
    assert f"| `{spaced(payload[4:])}` | `data` (float64)" in DOC
    assert topic.ups_payload(payload) == b"\x00\x32"
    extra = attachment(1, 1_700_000_000 * 10**9, who)
    rows = [extra[:8], extra[8:16], extra[16:17], extra[17:]]
    assert all(f"| `{spaced(row)}` |" in DOC for row in rows)
    assert DOC.count(RMW_ZENOH_COMMIT) >= 2


def test_the_forwarding_rule_is_the_one_the_processes_test_shows() -> None:
    """UPS -> ROS opens for any Zenoh subscriber whose key expression matches, ``**`` too, as
    tests/test_ros2_processes.py shows with real processes (the page used to say only a ROS
    subscriber of the exact key)."""
    from . import test_ros2_processes

    assert hasattr(test_ros2_processes, "test_any_zenoh_subscriber_whose_key_matches_turns_"
                   "forwarding_on")  # fmt: skip
    rule = DOC[DOC.index("## Forwarding") :].split("\n- **ROS → UPS")[0]
    assert "**UPS → ROS only while a Zenoh subscriber matches the topic's key.**" in rule
    assert "exact key" not in rule
    assert "`**`" in rule and "`to_ros` topic of the map" in rule
