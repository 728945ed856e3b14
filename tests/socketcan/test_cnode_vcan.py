"""The SocketCAN examples of libups (c/examples: ups-sensor, ups-actuator) on a real vcan0
inside User-Mode Linux, exchanging events with ``ups can-broker``, ``ups sub`` and ``ups pub``."""

from __future__ import annotations

import json
import subprocess

import pytest

from ..procs import ROOT, Proc, vcan_bus

pytestmark = pytest.mark.socketcan

BUILD = ROOT / "c" / "build"


def build_examples() -> None:
    subprocess.run(["make", "-s", "-C", str(ROOT / "c"), "examples"], check=True, timeout=300)


def test_sensor_and_actuator_with_the_python_tools(tmp_path: object) -> None:
    bus = vcan_bus()
    build_examples()
    db = f"{tmp_path}/ecb.db"
    with Proc("can-broker", "--can", bus, "--db", db, "--recovery", "0.3") as ecb:
        ecb.wait_for_line("CAN-ECB", timeout=60)
        actuator = subprocess.Popen(
            [str(BUILD / "ups-actuator"), "vcan0", "0xA1", "3"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            assert actuator.stderr is not None
            line = actuator.stderr.readline()  # bound: robot/cmd has its etag
            assert "robot/cmd at etag" in line, line
            with Proc("pub", "robot/cmd", "0a0b", "--can", bus, "--count", "3", "--rate", "10",
                      "--node-id", "0x52") as pub:  # fmt: skip
                assert pub.finish(timeout=120)[0] == 0
            out, _ = actuator.communicate(timeout=60)
            assert actuator.returncode == 0
            lines = out.splitlines()
            assert len(lines) == 3 and all(x.startswith("robot/cmd 0a0b from 0x") for x in lines)
        finally:
            if actuator.poll() is None:
                actuator.kill()
                actuator.wait()
        with Proc("sub", "robot/speed", "--can", bus, "--json", "--count", "3", "--timeout",
                  "120", "--node-id", "0x51") as sub:  # fmt: skip
            sub.wait_for_line("subscribed to", timeout=120)
            sensor = subprocess.run(
                [str(BUILD / "ups-sensor"), "vcan0", "0xA2", "3", "50"],
                capture_output=True,
                text=True,
                timeout=120,
                check=False,
            )
            assert sensor.returncode == 0, sensor.stderr
            code, out = sub.finish(timeout=120)
        assert code == 0
        assert [json.loads(x)["data"] for x in out.splitlines()] == ["0000", "0001", "0002"]
