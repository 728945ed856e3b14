"""A rogue on the ROS 2 router against ``ups ros2`` (issue 41): a real bridge between a CAN bus
(udp_multicast, with its CAN-ECB) and ``ups zenoh-router``, in a private network namespace;
the rogue is a plain Zenoh session putting rmw_zenoh-shaped samples on a topic's key, as
tests/test_ros2_processes.py's ROS side does, as fast as it can.

What it shows: 50,000 samples put as fast as Zenoh takes them become at most
``burst + max_rate * elapsed`` CAN frames (counted on the bus by a python-can listener), the
rest counted (``rate_limited``, in ``ups status`` and the metrics); a topic's own ``max_rate``
holds as its default does; a forged attachment sequence number of 2^62 is a jump
(``ros_jumps``), not 4.6e18 samples lost, while a real gap still counts as lost. Before,
50,000 samples were 50,000 frames and ``ros_lost`` rose by 2^62.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import threading
import time
import urllib.error
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from ups._canlink import open_bus
from ups._canproto import is_management, split_id

from .metrics_scrape import Scrape, metrics_url, scrape
from .procs import ROOT, Proc, private_multicast_bus
from .test_ros2_processes import CDR, FLOAT64
from .test_zenoh_processes import start_router, zenoh_status

pytestmark = [pytest.mark.netns, pytest.mark.timeout(180)]

DEFAULT_RATE, DEFAULT_BURST = 100.0, 20  # docs/ros2.md's defaults (test_ros2_doc ties them)
SLOW_RATE, SLOW_BURST = 25.0, 5
NODE = "ups_flood_bridge"
BRIDGE_ID = 0x5060
FLOOD = 50_000

CATALOG = """
[channel."robot/limit"]
byte_order = "big"
fields = [{ name = "limit", type = "i16", scale = 0.01, unit = "m/s" }]

[channel."robot/slow"]
byte_order = "big"
fields = [{ name = "limit", type = "i16", scale = 0.01, unit = "m/s" }]
"""
MAP = f"""
catalog = "catalog.toml"
node = "{NODE}"

[topic."/robot/limit"]
channel = "robot/limit"
type = "std_msgs/msg/Float64"
direction = "from_ros"
fields.data = "limit"
"""
#: a second bridge's: a topic with a bound of its own
SLOW_MAP = f"""
catalog = "catalog.toml"
node = "ups_slow_bridge"

[topic."/robot/slow"]
channel = "robot/slow"
type = "std_msgs/msg/Float64"
direction = "from_ros"
fields.data = "limit"
max_rate = {SLOW_RATE}
burst = {SLOW_BURST}
"""

#: The rogue: a plain Zenoh session (no ROS node, no token) with a publisher on a topic's key,
#: congestion control BLOCK so that every sample reaches the router. argv[1]: endpoint, key,
#: payload (hex), gid (hex), and count (sequence numbers 1..count) or sequences. It says
#: "ready" once the bridge's subscriber matches, puts when told "go", then says "done N S".
ROGUE = r"""
import json, struct, sys, time, zenoh
cfg = json.loads(sys.argv[1])
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([cfg["endpoint"]]))
session = zenoh.open(conf)
pub = session.declare_publisher(cfg["key"], congestion_control=zenoh.CongestionControl.BLOCK)
deadline = time.monotonic() + 60
while not pub.matching_status.matching and time.monotonic() < deadline:
    time.sleep(0.02)
print("ready", flush=True)
sys.stdin.readline()
payload, gid = bytes.fromhex(cfg["payload"]), bytes.fromhex(cfg["gid"])
numbers = cfg.get("sequences") or range(1, cfg["count"] + 1)
head = struct.Struct("<qqB")
start = time.monotonic()
for seq in numbers:
    pub.put(payload, attachment=head.pack(seq, time.time_ns(), 16) + gid)
print(f"done {len(numbers)} {time.monotonic() - start:.3f}", flush=True)
sys.stdin.read()
pub.undeclare()
session.close()
"""


class Rogue:
    """The rogue as a process; ``put()`` has it put everything, as fast as it can."""

    def __init__(self, endpoint: str, topic: str, gid: int, **numbers: Any) -> None:
        key = f"0/{topic.strip('/')}/std_msgs::msg::dds_::Float64_/{FLOAT64}"
        config = {"endpoint": endpoint, "key": key, "gid": f"{gid:032x}",
                  "payload": (CDR + struct.pack("<d", 0.5)).hex(), **numbers}  # fmt: skip
        self.popen = subprocess.Popen(
            [sys.executable, "-c", ROGUE, json.dumps(config)], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ},
        )  # fmt: skip
        assert self.popen.stdout is not None and self.popen.stdin is not None
        ready = self.popen.stdout.readline()
        assert ready.strip() == "ready", f"the rogue did not start: {ready!r}"

    def put(self) -> tuple[int, float]:
        """How many it put, in how many seconds."""
        assert self.popen.stdout is not None and self.popen.stdin is not None
        self.popen.stdin.write("go\n")
        self.popen.stdin.flush()
        _, count, seconds = self.popen.stdout.readline().split()
        return int(count), float(seconds)

    def __enter__(self) -> Rogue:
        return self

    def __exit__(self, *exc: object) -> None:
        assert self.popen.stdin is not None
        self.popen.stdin.close()
        try:
            self.popen.wait(timeout=30)
        finally:
            if self.popen.poll() is None:
                self.popen.kill()
                self.popen.wait()


class Frames:
    """Event frames on the bus, per TxNode, as a python-can listener on it sees them."""

    def __init__(self, bus: str) -> None:
        self.bus = open_bus(bus)
        self.counts: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._stop.is_set():
            frame = self.bus.recv(timeout=0.1)
            if (
                frame is not None
                and frame.is_extended_id
                and not is_management(frame.arbitration_id)
            ):
                txnode = split_id(frame.arbitration_id)[1]
                self.counts[txnode] = self.counts.get(txnode, 0) + 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.bus.shutdown()


@dataclass
class System:
    bus: str
    endpoint: str
    bridge: Proc
    frames: Frames
    tmp: Path


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[System]:
    """A CAN bus with its CAN-ECB and a listener, a Zenoh router, ``ups ros2`` between."""
    bus = private_multicast_bus()
    tmp = tmp_path_factory.mktemp("ros2flood")
    (tmp / "catalog.toml").write_text(CATALOG)
    (tmp / "map.toml").write_text(MAP)
    (tmp / "slow.toml").write_text(SLOW_MAP)
    endpoint = "tcp/127.0.0.1:17451"
    with (
        Proc("can-broker", "--can", bus, "--db", str(tmp / "ecb.db"), "--recovery", "0.2") as ecb,
        start_router(endpoint),
    ):
        ecb.wait_for_line("CAN-ECB on")
        frames = Frames(bus)
        try:
            with bridge_proc(tmp / "map.toml", endpoint, bus, BRIDGE_ID) as bridge:
                yield System(bus, endpoint, bridge, frames, tmp)
        finally:
            frames.close()


def bridge_proc(path: Path, endpoint: str, bus: str, node_id: int) -> Proc:
    proc = Proc("ros2", "--map", str(path), "--ros", endpoint, "--can", bus, "--node-id",
                hex(node_id), "--metrics", "127.0.0.1:0")  # fmt: skip
    try:
        proc.wait_for_line(r"ups ros2: ROS 2 node /\w+ on .*: 1 topics", 60)
    except BaseException:
        proc.stop()
        raise
    return proc


def counted(url: str, ready: Any, timeout: float = 90.0) -> Scrape:
    """Scrape the bridge until ``ready`` says the samples have been counted (a scrape the
    bridge's busy loop answers 503 is tried again); fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    found: Scrape | None = None
    while True:
        try:
            found = scrape(url)
            if ready(found):
                return found
        except (urllib.error.URLError, TimeoutError):
            pass
        if time.monotonic() > deadline:
            raise AssertionError(f"not counted within {timeout} s:\n{found and found.text}")
        time.sleep(0.1)


def value(found: Scrape, counter: str) -> float:
    return found.get(f"ups_ros2_{counter}_total", 0.0)


HANDLED = ("from_ros", "rate_limited", "rx_overflow", "malformed", "out_of_range")


def flood(system: System, bridge: Proc, topic: str, count: int, gid: int) -> dict[str, float]:
    """``count`` samples on ``topic`` as fast as the rogue can: the frames ``bridge`` put on
    the bus meanwhile, its counters' growth, and the seconds from "go" to the last sample
    counted (every frame it sent was sent within them)."""
    url = metrics_url(bridge)
    txnode = int(node_info(system.endpoint, bridge)["stats"]["txnode"])
    before = scrape(url)
    on_bus = system.frames.counts.get(txnode, 0)
    with Rogue(system.endpoint, topic, gid=gid, count=count) as rogue:
        start = time.monotonic()
        put, put_seconds = rogue.put()
        after = counted(url, lambda s: sum(value(s, c) - value(before, c) for c in HANDLED) >= put)
        elapsed = time.monotonic() - start
    grew = {c: value(after, c) - value(before, c) for c in (*HANDLED, "ros_lost", "ros_jumps")}
    deadline = time.monotonic() + 10  # the frames of what was counted, still on their way

    def sent() -> int:
        return system.frames.counts.get(txnode, 0) - on_bus

    while sent() < grew["from_ros"] and time.monotonic() < deadline:
        time.sleep(0.05)
    return {**grew, "frames": sent(), "put": put, "put_seconds": put_seconds,
            "elapsed": elapsed}  # fmt: skip


def node_info(endpoint: str, bridge: Proc) -> dict[str, Any]:
    """``ups status --zenoh`` of the bridge ``bridge`` (by its --node-id)."""
    node_id = int(bridge.args[bridge.args.index("--node-id") + 1], 0)
    for entry in zenoh_status(endpoint):
        if entry["node_id"] == f"0x{node_id:016x}":
            return entry
    return {}


def topic_of(endpoint: str, bridge: Proc, topic: str) -> dict[str, Any]:
    """The bridge's ``topic`` in ``ups status``."""
    topics = node_info(endpoint, bridge)["ros2"]["topics"]
    return dict(next(t for t in topics if t["topic"] == topic))


def test_50000_samples_from_a_rogue_are_bounded_on_can_and_the_excess_counted(
    system: System,
) -> None:
    got = flood(system, system.bridge, "/robot/limit", FLOOD, gid=0x5E01)
    print(f"\n{FLOOD} samples on /robot/limit: {got}")
    bound = DEFAULT_BURST + DEFAULT_RATE * got["elapsed"]
    assert got["put"] == FLOOD
    assert got["frames"] <= bound, f"{got['frames']} frames on CAN, the bound {bound:.0f}"
    assert got["frames"] == got["from_ros"] >= DEFAULT_BURST  # one frame each, none lost
    assert got["rate_limited"] == FLOOD - got["from_ros"]
    assert got["ros_lost"] == 0 and got["rx_overflow"] == 0
    # in ups status (the bridge's stats and the topic's), and in the metrics as documented
    endpoint, bridge = system.endpoint, system.bridge
    assert node_info(endpoint, bridge)["ros2"]["stats"]["rate_limited"] >= got["rate_limited"]
    info = topic_of(endpoint, bridge, "/robot/limit")
    assert info["rate_limited"] == got["rate_limited"]
    assert (info["max_rate"], info["burst"]) == (DEFAULT_RATE, DEFAULT_BURST)
    ours = [m for m in scrape(metrics_url(bridge)).undocumented() if m.startswith("ups_ros2_")]
    assert ours == []


def test_a_topics_own_max_rate_holds(system: System) -> None:
    """A second bridge, whose map gives its topic ``max_rate = 25`` and ``burst = 5``."""
    count = 10_000
    with bridge_proc(system.tmp / "slow.toml", system.endpoint, system.bus, BRIDGE_ID + 1) as slow:
        got = flood(system, slow, "/robot/slow", count, gid=0x5E02)
        info = topic_of(system.endpoint, slow, "/robot/slow")
    print(f"\n{count} samples on /robot/slow: {got}")
    bound = SLOW_BURST + SLOW_RATE * got["elapsed"]
    assert got["frames"] <= bound, f"{got['frames']} frames on CAN, the bound {bound:.0f}"
    assert got["frames"] == got["from_ros"] >= SLOW_BURST
    assert got["rate_limited"] == count - got["from_ros"] == info["rate_limited"]
    assert (info["max_rate"], info["burst"]) == (SLOW_RATE, SLOW_BURST)


def test_a_forged_sequence_number_is_a_jump_not_loss(system: System) -> None:
    """The rogue's numbers 1, 2, 4 (3 lost), 2^62 (forged), 5 (back): one lost, two jumps."""
    url = metrics_url(system.bridge)
    before = scrape(url)
    with Rogue(system.endpoint, "/robot/limit", gid=0x5EF0, sequences=[1, 2, 4, 2**62, 5]) as r:
        assert r.put()[0] == 5
        after = counted(url, lambda s: sum(value(s, c) - value(before, c) for c in HANDLED) >= 5)
    lost = value(after, "ros_lost") - value(before, "ros_lost")
    assert lost == 1, f"ros_lost rose by {lost:.3g}"
    assert value(after, "ros_jumps") - value(before, "ros_jumps") == 2
    assert node_info(system.endpoint, system.bridge)["ros2"]["stats"]["ros_jumps"] >= 2
