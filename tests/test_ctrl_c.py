"""Ctrl-C (SIGINT) ends ``ups demo``, ``ups demo --jaus``, ``ups jaus`` and ``ups jaus-ocu``
cleanly, each a process as a user runs it: exit 130, as a shell reports an interrupted
command, and nothing on stderr of a traceback or of a task left behind."""

from __future__ import annotations

import re
import signal

import pytest

from .procs import ROOT, Proc, start_tcp_broker

pytestmark = pytest.mark.timeout(240)

LEFT_BEHIND = ("Traceback", "Task exception was never retrieved", "Task was destroyed")


def interrupted(proc: Proc) -> str:
    """SIGINT ``proc``; it must exit 130 with a clean stderr, which is returned."""
    proc.popen.send_signal(signal.SIGINT)
    code, _ = proc.finish(timeout=60)
    stderr = "".join(proc.stderr_lines)
    assert code == 130, stderr
    assert not any(text in stderr for text in LEFT_BEHIND), stderr
    return stderr


def test_ctrl_c_ends_the_jaus_demo_and_a_watching_ocu() -> None:
    """While the demo's parts run and an OCU watches a 10 Hz event (its component's events,
    the robot's tasks and nodes all busy)."""
    with Proc("demo", "--jaus", "127.0.0.1:0") as demo:
        line = demo.wait_for_line(r"JAUS component 1\.1\.1 of the robot on", 120, stdout=True)
        found = re.search(r" on (127\.0\.0\.1:\d+) ", line)
        assert found is not None, line
        with Proc("jaus-ocu", "--target", found.group(1), "watch", "GlobalPose",
                  "--rate", "10") as watch:  # fmt: skip
            watch.wait_for_line("ReportGlobalPose", 60, stdout=True)  # events are coming
            interrupted(watch)
        interrupted(demo)


def test_ctrl_c_ends_the_plain_demo() -> None:
    with Proc("demo", "--duration", "120") as demo:
        demo.wait_for_line(r"dashboard: robot/speed", 120, stdout=True)
        interrupted(demo)


def test_ctrl_c_ends_ups_jaus() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    mapping = str(ROOT / "examples" / "robot.jaus.toml")
    with broker, Proc("jaus", "--listen", "127.0.0.1:0", "--map", mapping,
                      "--broker", address) as component:  # fmt: skip
        component.wait_for_line(r"JAUS component 1\.1\.1 on", 60)
        interrupted(component)
