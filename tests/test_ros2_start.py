"""``ups ros2`` and its ROS 2 router, as docs/ros2.md's recipe starts them: the router may come
after the bridge (the bridge waits for it as it waits for its CAN-ECB, up to ``--timeout``),
one that never comes is one line saying what to start, and ``--ros HOST:PORT`` is told the
form at once, before anything is joined. Real processes: a CAN-ECB on udp_multicast and
``ups zenoh-router``, inside a private network namespace.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from .procs import ROOT, Proc, private_multicast_bus
from .test_ros2_processes import ros_side
from .test_tcp_processes import wait_until
from .test_zenoh_processes import start_router

pytestmark = [pytest.mark.netns, pytest.mark.timeout(180)]

MAP = str(ROOT / "examples" / "robot.ros2.toml")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def bus(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A udp_multicast bus with its CAN-ECB."""
    bus = private_multicast_bus()
    db = tmp_path_factory.mktemp("ros2-start") / "ecb.db"
    with Proc("can-broker", "--can", bus, "--db", str(db), "--recovery", "0.2") as ecb:
        ecb.wait_for_line("CAN-ECB on")
        yield bus


def bridge_tokens(endpoint: str) -> list[str]:
    """The liveliness tokens of the demo map's bridge node in the ROS graph at ``endpoint``."""
    with ros_side(endpoint, "graph") as graph:
        return [t for t in graph.lines()[0]["tokens"] if "/%/%/ups_robot" in t]


def test_the_bridge_waits_for_a_ros_router_that_starts_after_it(bus: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Proc("ros2", "--map", MAP, "--ros", endpoint, "--can", bus, "--node-id",
              "0x5060") as bridge:  # fmt: skip
        bridge.wait_for_line(rf"waiting for the ROS 2 router at {endpoint} \(up to 30 s\)", 60)
        with start_router(endpoint):
            bridge.wait_for_line(r"ups ros2: ROS 2 node /ups_robot on .*: 7 topics", 60)
            wait_until(lambda: any("/NN/" in t for t in bridge_tokens(endpoint)), timeout=30)
        assert bridge.popen.poll() is None


def test_a_ros_router_that_never_comes_is_one_line_saying_what_to_start(bus: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Proc("ros2", "--map", MAP, "--ros", endpoint, "--can", bus, "--node-id", "0x5061",
              "--timeout", "5") as bridge:  # fmt: skip
        code, _ = bridge.finish(timeout=90)
    last = bridge.stderr_lines[-1]
    assert code == 2
    assert last.startswith(f"ups ros2: could not join the ROS 2 router at {endpoint} within 5 s")
    assert "ros2 run rmw_zenoh_cpp rmw_zenohd" in last
    assert f"ups zenoh-router --listen {endpoint}" in last
    assert ".rs:" not in "".join(bridge.stderr_lines)  # none of Zenoh's Rust source paths
    assert "Traceback" not in "".join(bridge.stderr_lines)


def test_ros_host_port_is_told_the_form_before_anything_is_joined(tmp_path: Path) -> None:
    """No CAN-ECB serves this bus: the endpoint is refused before the bridge waits for one."""
    bus = private_multicast_bus()
    with Proc("ros2", "--map", MAP, "--ros", "127.0.0.1:7447", "--can", bus,
              "--timeout", "60") as bridge:  # fmt: skip
        code, _ = bridge.finish(timeout=30)
    assert code == 2
    assert bridge.stderr_lines[-1].strip() == (
        "ups ros2: bad ROS 2 router endpoint '127.0.0.1:7447': it names no protocol "
        "(did you mean --ros tcp/127.0.0.1:7447?)"
    )
    assert not any("waiting for the CAN-ECB" in line for line in bridge.stderr_lines)
