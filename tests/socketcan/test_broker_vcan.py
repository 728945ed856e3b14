"""A bus with no Python CAN-ECB on it, on a real vcan0 inside User-Mode Linux: the board example
(c/examples/broker.c: libups-ecb, the CAN-ECB in C, and a libups node in one image), the C
sensor and actuator, and ``ups sub``/``ups pub`` as ordinary nodes, exchanging events. No
``ups can-broker`` runs: every TxNode and etag comes from the C CAN-ECB.

The board keeps its blob in a file standing for flash; started again on it, the CAN-ECB takes
its state back: a node that joined before has its TxNode again."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest

from ..procs import ROOT, Proc, vcan_bus

pytestmark = [pytest.mark.socketcan, pytest.mark.timeout(600)]

BUILD = ROOT / "c" / "build"
WAIT = 120.0  # generous bounds on events: User-Mode Linux has one slow CPU


def build_examples() -> None:
    subprocess.run(["make", "-s", "-C", str(ROOT / "c"), "examples"], check=True, timeout=300)


def board(blob: Path, node_id: str = "0xB0", period_ms: int = 100) -> Proc:
    """ups-broker on vcan0: the CAN-ECB and its own node (publishes board/uptime every
    period_ms, prints robot/speed events)."""
    return Proc(shell=f"exec {BUILD / 'ups-broker'} vcan0 {node_id} {blob} {period_ms}")


def example(name: str, *args: str) -> Proc:
    return Proc(shell=" ".join(["exec", str(BUILD / f"ups-{name}"), "vcan0", *args]))


def said(proc: Proc, text: str) -> str:
    """The first stderr line so far that holds text (the lines come in no fixed order)."""
    found = [line for line in proc.stderr_lines if text in line]
    assert found, f"no {text!r} in:\n{''.join(proc.stderr_lines)}"
    return found[0]


def uptimes(out: str) -> list[int]:
    return [int(json.loads(line)["data"], 16) for line in out.splitlines()]


def test_c_can_ecb_board_serves_c_and_python_nodes(tmp_path: Path) -> None:
    bus = vcan_bus()
    build_examples()
    blob = tmp_path / "ecb.blob"
    with board(blob) as ecb:
        ecb.wait_for_line("board/uptime at etag", timeout=WAIT)  # through its own CAN-ECB
        assert said(ecb, "CAN-ECB serving")
        assert said(ecb, "joined as TxNode")
        # ups pub -> the C actuator
        with example("actuator", "0xA1", "3") as actuator:
            actuator.wait_for_line("robot/cmd at etag", timeout=WAIT)
            with Proc("pub", "robot/cmd", "0a0b", "--can", bus, "--count", "3", "--rate", "10",
                      "--node-id", "0x52") as pub:  # fmt: skip
                assert pub.finish(timeout=WAIT)[0] == 0
            code, out = actuator.finish(timeout=WAIT)
        assert code == 0, "".join(actuator.stderr_lines)
        lines = out.splitlines()
        assert len(lines) == 3 and all(x.startswith("robot/cmd 0a0b from 0x") for x in lines)
        # the C sensor -> ups sub and the board's own node
        with Proc("sub", "robot/speed", "--can", bus, "--json", "--count", "3", "--timeout",
                  str(int(WAIT)), "--node-id", "0x51") as sub:  # fmt: skip
            sub.wait_for_line("subscribed to", timeout=WAIT)
            sensor = subprocess.run(
                [str(BUILD / "ups-sensor"), "vcan0", "0xA2", "3", "50"],
                capture_output=True,
                text=True,
                timeout=WAIT,
                check=False,
            )
            assert sensor.returncode == 0, sensor.stderr
            code, out = sub.finish(timeout=WAIT)
        assert code == 0
        assert [json.loads(x)["data"] for x in out.splitlines()] == ["0000", "0001", "0002"]
        heard = ecb.wait_for_stdout(3, timeout=WAIT)
        assert [x.split()[:2] for x in heard[:3]] == [["robot/speed", s] for s in
                                                      ("0000", "0001", "0002")]  # fmt: skip
        # the board's node -> ups sub
        with Proc("sub", "board/uptime", "--can", bus, "--json", "--count", "2", "--timeout",
                  str(int(WAIT)), "--node-id", "0x53") as sub:  # fmt: skip
            code, out = sub.finish(timeout=WAIT)
        assert code == 0
        first, second = uptimes(out)
        assert second > first
        assert ecb.stop() == 0, "".join(ecb.stderr_lines)
    stopped = ecb.stderr_lines[-1]
    assert "CAN-ECB serving" in stopped, stopped
    written = re.search(r"(\d+) joined, (\d+) bound, (\d+) state writes", stopped)
    assert written is not None, stopped
    # 6 nodes (board, actuator, pub, sub, sensor, sub) and 3 channels at least; the blob changes
    # with a new node or a new binding only
    nodes, bindings, writes = (int(n) for n in written.groups())
    assert nodes >= 6 and bindings >= 3, stopped
    assert 1 <= writes <= nodes + bindings, (
        f"the blob written more often than it changed: {stopped}"
    )
    assert blob.stat().st_size > 0


def test_c_can_ecb_board_takes_its_state_back_from_its_blob(tmp_path: Path) -> None:
    """Started again on its blob, the CAN-ECB gives a known node its TxNode and its channel its
    etag again, whoever asks first; a new node gets another TxNode. (With no blob the new node,
    asking first, would get the old one's TxNode.)"""
    vcan_bus()
    build_examples()
    blob = tmp_path / "ecb.blob"
    with board(blob) as ecb:
        ecb.wait_for_line("board/uptime at etag", timeout=WAIT)
        with example("actuator", "0xA1", "1") as actuator:
            first = actuator.wait_for_line("robot/cmd at etag", timeout=WAIT)
        assert ecb.stop() == 0, "".join(ecb.stderr_lines)
    with board(blob) as ecb:
        ecb.wait_for_line("board/uptime at etag", timeout=WAIT)
        assert said(ecb, "state taken back")
        with example("sensor", "0xA2", "1", "50") as sensor:
            assert sensor.finish(timeout=WAIT)[0] == 0, "".join(sensor.stderr_lines)
        newcomer = said(sensor, "joined as TxNode").split()[-1]
        with example("actuator", "0xA1", "1") as actuator:
            again = actuator.wait_for_line("robot/cmd at etag", timeout=WAIT)
        assert again == first  # the same TxNode and the same etag
        held = re.search(r"TxNode (0x\w+)", first)
        assert held is not None and held[1] != newcomer, (newcomer, first)
        assert ecb.stop() == 0, "".join(ecb.stderr_lines)


def line_with(proc: Proc, text: str) -> str:
    """The first stderr line that holds text, waiting for it if none came yet."""
    found = [line for line in proc.stderr_lines if text in line]
    return found[0] if found else proc.wait_for_line(re.escape(text), timeout=WAIT)


def test_two_boards_one_serves_the_other_takes_over(tmp_path: Path) -> None:
    """Two boards carry the CAN-ECB: the one started second stands by (its node joins through
    the first); the first stops, and the second takes over and serves new nodes."""
    bus = vcan_bus()
    build_examples()
    with board(tmp_path / "a.blob", "0xB0") as first:
        first.wait_for_line("board/uptime at etag", timeout=WAIT)
        with board(tmp_path / "b.blob", "0xB1") as second:
            second.wait_for_line("board/uptime at etag", timeout=WAIT)
            assert line_with(second, "CAN-ECB standing by")
            assert not [x for x in second.stderr_lines if "CAN-ECB serving" in x]
            assert first.stop() == 0, "".join(first.stderr_lines)
            assert "CAN-ECB serving" in first.stderr_lines[-1]
            line_with(second, "CAN-ECB serving")  # took over
            with example("actuator", "0xA1", "2") as actuator:
                actuator.wait_for_line("robot/cmd at etag", timeout=WAIT)
                with Proc("pub", "robot/cmd", "0a0b", "--can", bus, "--count", "2", "--rate",
                          "10", "--node-id", "0x52") as pub:  # fmt: skip
                    assert pub.finish(timeout=WAIT)[0] == 0
                code, out = actuator.finish(timeout=WAIT)
            lines = out.splitlines()
            assert code == 0 and len(lines) == 2, "".join(actuator.stderr_lines)
            assert all(x.startswith("robot/cmd 0a0b from 0x") for x in lines)
            with Proc("sub", "board/uptime", "--can", bus, "--json", "--count", "2", "--timeout",
                      str(int(WAIT)), "--node-id", "0x53") as sub:  # fmt: skip
                code, out = sub.finish(timeout=WAIT)
            assert code == 0 and len(uptimes(out)) == 2  # the second board's own node
            assert second.stop() == 0, "".join(second.stderr_lines)
        assert "CAN-ECB serving" in second.stderr_lines[-1]
