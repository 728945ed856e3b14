"""Examples are product: the demo must run and show every channel, the brake included, on CAN
and through the gateway on TCP/IP."""

from __future__ import annotations

import json
import socket
import time

import pytest

from .procs import Proc, private_multicast_bus


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_demo_runs_and_brakes() -> None:
    demo = Proc("demo", "--duration", "2.5")
    code, out = demo.finish(timeout=60)
    assert code == 0, "".join(demo.stderr_lines)
    assert "robot/brake admitted as real-time, priority 0x02" in out
    assert "dashboard: BRAKE from TxNode 0x03 (priority 0x02)" in out
    assert "wheel-encoder: speed limit 30 cm/s from TxNode 0x00" in out  # TCP -> gateway -> CAN
    assert "operator (TCP): BRAKE via the gateway (priority 0x02)" in out  # CAN -> TCP
    assert "gets a TxNode" in out.split("gateway:")[0]  # it says what it will show, first
    assert "In short: everything arrived." in out and "Try next" in out


@pytest.mark.netns
def test_the_robot_runs_as_processes_that_tools_can_watch() -> None:
    bus = private_multicast_bus()
    port = free_port()
    demo = Proc("demo", "--processes", "--can", bus, "--listen", f"127.0.0.1:{port}",
                "--duration", "30")  # fmt: skip
    with demo:
        code, out = Proc("sub", "robot/speed", "--can", bus, "--count", "3",
                         "--timeout", "25").finish(timeout=30)  # fmt: skip
        assert code == 0 and out.count("robot/speed  00") == 3  # another process hears it
        ls = Proc("ls", "--broker", f"127.0.0.1:{port}", "--json")
        code, out = ls.finish()
        assert code == 0, ls.stderr_lines
        assert {"operator", "ups-gateway"} <= {n["name"] for n in json.loads(out)["nodes"]}
        deadline = time.monotonic() + 25
        while not all(line in "".join(demo.stdout_lines)
                      for line in ("BRAKE via the gateway", "speed limit 30")):  # fmt: skip
            assert time.monotonic() < deadline, demo.stdout_lines
            time.sleep(0.05)
    assert demo.popen.returncode == 0, "".join(demo.stdout_lines + demo.stderr_lines)
    printed = "".join(demo.stdout_lines)
    assert "[dashboard] dashboard: BRAKE from TxNode" in printed
    assert "ups monitor --can" in printed and "In short: everything arrived." in printed
