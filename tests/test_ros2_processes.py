"""``ups ros2`` as a process between a CAN bus (udp_multicast, with its CAN-ECB) and a Zenoh
router (``ups zenoh-router``), inside a private network namespace, against a ROS 2 side written
here from rmw_zenoh's docs/design.md alone (no code of ``ups.ros2``): its key expressions,
liveliness tokens, attachment and GIDs, and CDR by hand.

What it shows: CAN events arrive as typed messages whose attachments carry consecutive sequence
numbers from 1 and the GID of the bridge's publisher token; nothing is put on Zenoh before a
subscriber of that key matches, nor after it leaves (the numbers go on where they stopped); a
listener of another type or domain gets nothing and makes the bridge open nothing, while a
plain Zenoh subscriber of ``**`` (no ROS node) opens every topic sent to ROS;
rmw_zenoh-shaped publications reach a CAN subscriber as the catalog's bytes; values out of
range and NaN into an integer are dropped and counted; a Twist crosses classic CAN (a 24-byte
event: several frames) both ways, never reflected.
"""

from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import xxhash

from ups import name_to_uid
from ups.ros2._serve import ROS2

from .metrics_scrape import metrics_url, scrape, uncovered
from .procs import ROOT, Proc, private_multicast_bus
from .test_tcp_processes import wait_until
from .test_zenoh_processes import start_router, zenoh_status

pytestmark = [pytest.mark.netns, pytest.mark.timeout(300)]

# the type hashes ROS 2 generates (tests/test_ros2_reference.py checks them against rclpy's)
INT16 = "RIHS01_1dcc3464e47c288a55f943a389d337cdb06804de3f5cd7a266b0de718eee17e5"
FLOAT64 = "RIHS01_705ba9c3d1a09df43737eb67095534de36fd426c0587779bda2bc51fe790182a"
STRING = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
TWIST = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
NODE = "ups_test_bridge"

CATALOG = """
[channel."robot/speed"]
byte_order = "big"
fields = [{ name = "speed", type = "i16", unit = "cm/s" }]

[channel."robot/limit"]
byte_order = "big"
fields = [{ name = "limit", type = "i16", scale = 0.01, unit = "m/s" }]

[channel."robot/label"]
fields = [{ name = "level", type = "u8" }, { name = "text", type = "str" }]

[channel."robot/cmd"]
fields = [{ name = "vx", type = "f32" }, { name = "vy", type = "f32" },
          { name = "vz", type = "f32" }, { name = "wx", type = "f32" },
          { name = "wy", type = "f32" }, { name = "wz", type = "f32" }]
"""
MAP = f"""
catalog = "catalog.toml"
node = "{NODE}"

[topic."/robot/speed"]
channel = "robot/speed"
type = "std_msgs/msg/Int16"
fields.data = "speed"

[topic."/robot/limit"]
channel = "robot/limit"
type = "std_msgs/msg/Float64"
direction = "from_ros"
fields.data = "limit"

[topic."/robot/label"]
channel = "robot/label"
type = "std_msgs/msg/String"
direction = "from_ros"
fields.data = "text"
ups_constants = {{ level = 3 }}

[topic."/robot/cmd_vel"]
channel = "robot/cmd"
type = "geometry_msgs/msg/Twist"
direction = "both"
fields.linear = {{ x = "vx", y = "vy", z = "vz" }}
fields.angular = {{ x = "wx", y = "wy", z = "wz" }}
"""

#: A ROS 2 participant as rmw_zenoh's docs/design.md describes one, in a few lines of zenoh:
#: argv[1] is a JSON object: mode ("listen", "publish", "graph", or "plain": a subscriber of the
#: key expression "key" with no ROS node or token), endpoint, domain, topic, type
#: ("pkg/msg/Type"), hash, and for "publish" the payloads (hex; "plain:": no attachment).
ROS_SIDE = r"""
import json, os, struct, sys, time, zenoh, xxhash
cfg = json.loads(sys.argv[1])
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([cfg["endpoint"]]))
session = zenoh.open(conf)
zid, domain = str(session.zid()), cfg["domain"]
if cfg["mode"] == "graph":  # what ros2 topic list reads: every liveliness token of the domain
    tokens = [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{domain}/**")
              if r.ok is not None]
    print("ready", flush=True)
    print(json.dumps({"tokens": tokens}), flush=True)
    sys.stdin.read()
    session.close()
    os._exit(0)
if cfg["mode"] == "plain":  # a Zenoh program, no ROS node: a subscriber of cfg["key"], no token
    key, tokens = cfg["key"], []
else:
    pkg, _, name = cfg["type"].split("/")
    dds = f"{pkg}::msg::dds_::{name}_"
    key = f"{domain}/{cfg['topic'].strip('/')}/{dds}/{cfg['hash']}"
    node_name = "ros_side"
    node = f"@ros2_lv/{domain}/{zid}/0/0/NN/%/%/{node_name}"
    kind = "MS" if cfg["mode"] == "listen" else "MP"
    entity = (f"@ros2_lv/{domain}/{zid}/0/10/{kind}/%/%/{node_name}/"
              f"{cfg['topic'].replace('/', '%')}/{dds}/{cfg['hash']}/::,10:,:,:,,")
    tokens = [session.liveliness().declare_token(node),
              session.liveliness().declare_token(entity)]
if cfg["mode"] in ("listen", "plain"):
    def show(sample):
        att = sample.attachment
        print(json.dumps({"key": str(sample.key_expr), "data": sample.payload.to_bytes().hex(),
                          "attachment": None if att is None else att.to_bytes().hex()}),
              flush=True)
    sub = session.declare_subscriber(key, show)
    print("ready", flush=True)
    sys.stdin.read()
    sub.undeclare()
else:
    pub = session.declare_publisher(key)
    deadline = time.monotonic() + 60
    while not pub.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.02)
    gid = xxhash.xxh3_128(entity.encode()).intdigest().to_bytes(16, "little")
    for seq, data in enumerate(cfg["payloads"], start=1):
        if data.startswith("plain:"):
            pub.put(bytes.fromhex(data[6:]))
        else:
            att = struct.pack("<qqB", seq, time.time_ns(), 16) + gid
            pub.put(bytes.fromhex(data), attachment=att)
    print("ready", flush=True)
    sys.stdin.read()
for token in tokens:
    token.undeclare()
session.close()
os._exit(0)
"""

CDR = b"\x00\x01\x00\x00"  # plain CDR, little-endian


class RosSide:
    """The ROS side as a process: its JSON lines collected as they come; it stops when its
    stdin closes (``lines()``)."""

    def __init__(self, config: dict[str, Any]) -> None:
        self.popen = subprocess.Popen(
            [sys.executable, "-c", ROS_SIDE, json.dumps(config)], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ},
        )  # fmt: skip
        assert self.popen.stdout is not None
        ready = self.popen.stdout.readline()
        assert ready.strip() == "ready", f"the ROS side did not start: {ready!r}"
        self.seen: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.seen.append(json.loads(line))

    def lines(self) -> list[dict[str, Any]]:
        """Stop it; every line it printed."""
        assert self.popen.stdin is not None
        if not self.popen.stdin.closed:
            self.popen.stdin.close()
        self.popen.wait(timeout=30)
        self._reader.join(timeout=10)
        return list(self.seen)

    def __enter__(self) -> RosSide:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()


def ros_side(endpoint: str, mode: str, topic: str = "", ros_type: str = "", hash_: str = "",
             domain: int = 0, payloads: list[str] | None = None,
             key: str = "") -> RosSide:  # fmt: skip
    return RosSide({"mode": mode, "endpoint": endpoint, "domain": domain, "topic": topic,
                    "type": ros_type, "hash": hash_, "payloads": payloads or [],
                    "key": key})  # fmt: skip


def bridge_info(endpoint: str) -> dict[str, Any]:
    for entry in zenoh_status(endpoint):
        if "ros2" in entry:
            return entry
    return {}


def topic_info(endpoint: str, topic: str) -> dict[str, Any]:
    info = bridge_info(endpoint)
    for entry in info.get("ros2", {}).get("topics", []):
        if entry["topic"] == topic:
            return dict(entry)
    return {}


def samples(lines: list[dict[str, Any]]) -> list[tuple[int, int, bytes, bytes]]:
    """(sequence, source time, GID, payload) of each sample, checking the attachment's form."""
    out = []
    for line in lines:
        att = bytes.fromhex(line["attachment"])
        assert len(att) == 33 and att[16] == 16, att.hex()
        seq, when = struct.unpack_from("<qq", att)
        out.append((seq, when, att[17:], bytes.fromhex(line["data"])))
    return out


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, Proc]]:
    """A CAN bus with its CAN-ECB, a Zenoh router, and ``ups ros2`` between them."""
    bus = private_multicast_bus()
    tmp = tmp_path_factory.mktemp("ros2")
    (tmp / "catalog.toml").write_text(CATALOG)
    (tmp / "map.toml").write_text(MAP)
    endpoint = "tcp/127.0.0.1:17448"
    with (
        Proc("can-broker", "--can", bus, "--db", str(tmp / "ecb.db"), "--recovery", "0.2") as ecb,
        start_router(endpoint),
    ):
        ecb.wait_for_line("CAN-ECB on")
        with Proc("ros2", "--map", str(tmp / "map.toml"), "--ros", endpoint, "--can", bus,
                  "--node-id", "0x5052", "--metrics", "127.0.0.1:0") as bridge:  # fmt: skip
            bridge.wait_for_line(r"ups ros2: ROS 2 node /ups_test_bridge on .*: 4 topics", 60)
            yield bus, endpoint, bridge


def test_the_bridge_is_in_the_ros_graph_as_rmw_zenoh_would_be(
    system: tuple[str, str, Proc],
) -> None:
    _, endpoint, _ = system
    with ros_side(endpoint, "graph") as graph:
        tokens = graph.lines()[0]["tokens"]
    ours = [t for t in tokens if f"/%/%/{NODE}" in t]
    zid = ours[0].split("/")[2]
    assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/{NODE}" in ours
    publishers = [t.split("/")[5:] for t in ours if "/MP/" in t]
    subscriptions = [t.split("/")[5:] for t in ours if "/MS/" in t]
    assert ["MP", "%", "%", NODE, "%robot%speed", "std_msgs::msg::dds_::Int16_", INT16,
            "::,10:,:,:,,"] in publishers  # fmt: skip
    assert ["MP", "%", "%", NODE, "%robot%cmd_vel", "geometry_msgs::msg::dds_::Twist_", TWIST,
            "::,10:,:,:,,"] in publishers  # fmt: skip
    # on CAN the ROS subscriptions stay declared: the bus's subscribers are its CAN-ECB's
    assert ["MS", "%", "%", NODE, "%robot%limit", "std_msgs::msg::dds_::Float64_", FLOAT64,
            "::,10:,:,:,,"] in subscriptions  # fmt: skip


def test_can_events_reach_a_ros_listener_only_while_it_listens(
    system: tuple[str, str, Proc],
) -> None:
    bus, endpoint, _ = system
    speed = "/robot/speed"
    with ros_side(endpoint, "graph") as graph:
        token = next(t for t in graph.lines()[0]["tokens"] if f"/MP/%/%/{NODE}/%robot%speed/" in t)
    bridge_gid = xxhash.xxh3_128(token.encode()).intdigest().to_bytes(16, "little")
    with Proc("pub", "robot/speed", "0102", "--can", bus, "--count", "3000", "--rate", "50"):
        # listeners of another type and of another domain: nothing matches, nothing opens
        with (
            ros_side(endpoint, "listen", speed, "std_msgs/msg/Float64", FLOAT64) as wrong_type,
            ros_side(endpoint, "listen", speed, "std_msgs/msg/Int16", INT16, domain=1) as other,
        ):
            info = topic_info(endpoint, speed)
            assert info["to_ros_forwarding"] is False and info["sent"] == 0
            assert f"0x{name_to_uid('robot/speed'):016x}" not in bridge_info(endpoint)["subscribed"]
            with ros_side(endpoint, "listen", speed, "std_msgs/msg/Int16", INT16) as listener:
                wait_until(lambda: len(listener.seen) >= 5, timeout=60)
            first = samples(listener.lines())
            wait_until(lambda: topic_info(endpoint, speed)["to_ros_forwarding"] is False, 30)
            stopped_at = topic_info(endpoint, speed)["sequence"]
            assert wrong_type.lines() == [] and other.lines() == []
        # the first listener's numbers start at 1: nothing was put before it matched
        assert [s[0] for s in first] == list(range(1, len(first) + 1))
        assert {s[2] for s in first} == {bridge_gid}
        assert {s[3] for s in first} == {CDR + struct.pack("<h", 0x0102) + b"\x00\x00"}
        assert all(abs(s[1] - time.time_ns()) < 120e9 for s in first)
        # a second listener: the numbers go on where they stopped when the first one left
        with ros_side(endpoint, "listen", speed, "std_msgs/msg/Int16", INT16) as listener:
            wait_until(lambda: len(listener.seen) >= 3, timeout=60)
        again = samples(listener.lines())
    assert again[0][0] == stopped_at + 1
    assert [s[0] for s in again] == list(range(stopped_at + 1, stopped_at + 1 + len(again)))


def test_any_zenoh_subscriber_whose_key_matches_turns_forwarding_on(
    system: tuple[str, str, Proc],
) -> None:
    """docs/ros2.md, *Forwarding*: not only a ROS subscriber of the topic's exact key. A plain
    Zenoh subscriber of ``**`` (a recorder, a bridge, ``z_sub``: no ROS node, no liveliness
    token) turns every ``to_ros`` topic of the map on, and off again when it leaves; the
    numbers go on where they stopped."""
    bus, endpoint, _ = system
    topics = ("/robot/speed", "/robot/cmd_vel")  # the map's to_ros and both topics

    def forwarding() -> list[bool]:
        return [topic_info(endpoint, t)["to_ros_forwarding"] for t in topics]

    def of_speed(lines: list[dict[str, Any]]) -> list[dict[str, Any]]:
        return [line for line in lines if line["key"].startswith("0/robot/speed/")]

    with Proc("pub", "robot/speed", "0304", "--can", bus, "--count", "3000", "--rate", "50"):
        wait_until(lambda: forwarding() == [False, False], 30)  # nobody listens yet
        before = topic_info(endpoint, "/robot/speed")["sequence"]
        with ros_side(endpoint, "plain", key="**") as recorder:
            wait_until(lambda: len(of_speed(recorder.seen)) >= 3, timeout=60)
            wait_until(lambda: forwarding() == [True, True], 30)
            with ros_side(endpoint, "graph") as graph:  # and it is in no ROS graph
                assert not any("/ros_side" in t for t in graph.lines()[0]["tokens"])
        got = samples(of_speed(recorder.lines()))
        wait_until(lambda: forwarding() == [False, False], 30)
    assert [s[0] for s in got] == list(range(before + 1, before + 1 + len(got)))
    assert {s[3] for s in got} == {CDR + struct.pack("<h", 0x0304) + b"\x00\x00"}


def test_ros_publications_reach_a_can_subscriber_as_the_catalogs_bytes(
    system: tuple[str, str, Proc],
) -> None:
    bus, endpoint, bridge = system
    f64 = struct.Struct("<d")
    payloads = [
        (CDR + f64.pack(1.5)).hex(),  # 150 (scale 0.01)
        (CDR + f64.pack(400.0)).hex(),  # 40000: out of an i16's range, dropped
        (CDR + f64.pack(math.nan)).hex(),  # NaN into an integer: dropped
        (CDR + f64.pack(-0.25)).hex(),  # -25
        "plain:" + (CDR + f64.pack(2.0)).hex(),  # no attachment: forwarded, counted
    ]
    before = bridge_info(endpoint)["ros2"]["stats"]
    with Proc("sub", "robot/limit", "--can", bus, "--json", "--count", "3", "--timeout", "120",
              "--node-id", "0x5053") as can_sub:  # fmt: skip
        can_sub.wait_for_line("subscribed to")
        with ros_side(endpoint, "publish", "/robot/limit", "std_msgs/msg/Float64", FLOAT64,
                      payloads=payloads):  # fmt: skip
            code, out = can_sub.finish(timeout=120)
    assert code == 0
    assert [json.loads(line)["data"] for line in out.splitlines()] == ["0096", "ffe7", "00c8"]
    after = bridge_info(endpoint)["ros2"]["stats"]
    assert after["out_of_range"] - before["out_of_range"] == 2
    assert after["no_attachment"] - before["no_attachment"] == 1
    assert after["from_ros"] - before["from_ros"] == 3
    # a message larger than the channel's binding on CAN (one frame): bound larger, then sent
    text = "a label longer than one CAN frame"
    string = CDR + struct.pack("<I", len(text) + 1) + text.encode() + b"\x00"
    with Proc("sub", "robot/label", "--can", bus, "--json", "--count", "1", "--timeout", "120",
              "--node-id", "0x5057") as can_sub:  # fmt: skip
        can_sub.wait_for_line("subscribed to")
        with ros_side(endpoint, "publish", "/robot/label", "std_msgs/msg/String", STRING,
                      payloads=[string.hex()]):  # fmt: skip
            code, out = can_sub.finish(timeout=120)
    assert code == 0 and json.loads(out)["data"] == (b"\x03" + text.encode()).hex()
    # the same counters for Prometheus, each documented in docs/metrics.md
    metrics = scrape(metrics_url(bridge))
    assert metrics.value("ups_ros2_out_of_range_total") >= 2
    assert metrics.value("ups_ros2_from_ros_total") == after["from_ros"] + 1
    assert metrics.value("ups_node_published_total", network="can") >= 3
    assert metrics.undocumented() == []
    assert uncovered(after, [ROS2]) == set()


def test_a_twist_crosses_classic_can_both_ways_never_reflected(
    system: tuple[str, str, Proc],
) -> None:
    bus, endpoint, _ = system
    cmd = "/robot/cmd_vel"
    from_ros = (0.5, -1.25, 3.0, 0.0, 0.125, -0.75)
    from_can = (1.0, 0.0, 0.0, 0.0, 0.0, 0.5)
    twist = CDR + struct.pack("<6d", *from_ros)
    event = struct.pack("<6f", *from_can)
    with ros_side(endpoint, "graph") as graph:
        token = next(
            t for t in graph.lines()[0]["tokens"] if f"/MP/%/%/{NODE}/%robot%cmd_vel/" in t
        )
    bridge_gid = xxhash.xxh3_128(token.encode()).intdigest().to_bytes(16, "little")
    with (
        ros_side(endpoint, "listen", cmd, "geometry_msgs/msg/Twist", TWIST) as listener,
        Proc("sub", "robot/cmd", "--can", bus, "--json", "--count", "2", "--timeout", "120",
             "--node-id", "0x5054") as can_sub,
    ):  # fmt: skip
        can_sub.wait_for_line("subscribed to")
        wait_until(lambda: topic_info(endpoint, cmd)["to_ros_forwarding"] is True, 30)
        with ros_side(endpoint, "publish", cmd, "geometry_msgs/msg/Twist", TWIST,
                      payloads=[twist.hex()]):  # fmt: skip
            can_sub.wait_for_stdout(1, timeout=60)
            with Proc("pub", "robot/cmd", event.hex(), "--can", bus, "--node-id", "0x5055") as p:
                assert p.finish(timeout=60)[0] == 0
            code, out = can_sub.finish(timeout=120)
        wait_until(lambda: topic_info(endpoint, cmd)["sent"] >= 1, 30)
        got = listener.lines()
    assert code == 0
    assert [json.loads(line)["data"] for line in out.splitlines()] == [
        struct.pack("<6f", *from_ros).hex(),
        event.hex(),
    ]
    # from the bridge: the CAN event, as a Twist (52 bytes of CDR), once; the ROS publisher's
    # sample never comes back through the bridge
    from_bridge = [s for s in samples(got) if s[2] == bridge_gid]
    assert [s[3] for s in from_bridge] == [CDR + struct.pack("<6d", *from_can)]
    assert len(from_bridge[0][3]) == 52
    info = topic_info(endpoint, cmd)
    assert info["received"] == 1 and info["sent"] == 1
    assert bridge_info(endpoint)["ros2"]["stats"]["reflected"] >= 1


def test_on_zenoh_ros_is_heard_only_while_a_ups_node_subscribes(tmp_path: Path) -> None:
    """The UPS side on Zenoh (a router of its own): the bridge's ROS subscription (its ``MS``
    token) exists only while a UPS node subscribes to the channel, and the bridge answers
    ``ups status`` there."""
    (tmp_path / "catalog.toml").write_text(CATALOG)
    (tmp_path / "map.toml").write_text(MAP)
    ros, ups = "tcp/127.0.0.1:17449", "tcp/127.0.0.1:17450"

    def subscribed() -> bool:
        with ros_side(ros, "graph") as graph:
            tokens = graph.lines()[0]["tokens"]
        return any(f"/MS/%/%/{NODE}/%robot%limit/" in t for t in tokens)

    with (
        start_router(ros),
        start_router(ups),
        Proc("ros2", "--map", str(tmp_path / "map.toml"), "--ros", ros, "--zenoh", ups,
             "--node-id", "0x5056") as bridge,
    ):  # fmt: skip
        bridge.wait_for_line(r"ups ros2: ROS 2 node /ups_test_bridge on .*: 4 topics", 60)
        assert not subscribed()
        with Proc("sub", "robot/limit", "--zenoh", ups, "--json", "--count", "1", "--timeout",
                  "120") as sub:  # fmt: skip
            sub.wait_for_line("subscribed to")
            wait_until(subscribed, timeout=30)
            payload = (CDR + struct.pack("<d", 0.75)).hex()
            with ros_side(ros, "publish", "/robot/limit", "std_msgs/msg/Float64", FLOAT64,
                          payloads=[payload]):  # fmt: skip
                code, out = sub.finish(timeout=120)
        assert code == 0 and json.loads(out)["data"] == "004b"  # 75 (scale 0.01), big-endian
        wait_until(lambda: not subscribed(), timeout=30)
        entries = [e for e in zenoh_status(ups) if "ros2" in e]
        assert len(entries) == 1 and entries[0]["node_id"] == f"0x{0x5056:016x}"
        assert entries[0]["ros2"]["stats"]["from_ros"] == 1
