"""The first hour, as a new user types it: after the README's setup (``scripts/demo``), in new
shells whose PATH knows nothing of ``.venv``, the commands that the demo and ``scripts/setup``
print work as printed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .procs import ROOT, Proc, private_network

#: what a command that keeps running says once it is ready for the next one
READY = {"broker": "TCP-ECB on 127.0.0.1:7411", "sub": "subscribed to"}


def new_shell_environment() -> dict[str, str]:
    """A login's environment: no virtual environment active, no ``ups`` on the PATH."""
    here = str(Path(sys.executable).parent)
    path = [
        p for p in os.environ.get("PATH", "/usr/bin:/bin").split(os.pathsep)
        if p and p != here and not (Path(p) / "ups").exists()
    ]  # fmt: skip
    kept = {k: v for k, v in os.environ.items() if k in ("HOME", "USER", "LANG", "TMPDIR")}
    return {**kept, "PATH": os.pathsep.join(path)}


def test_scripts_setup_says_how_a_new_shell_finds_ups() -> None:
    env = new_shell_environment()
    assert subprocess.run(["bash", "-c", "command -v ups"], env=env, check=False).returncode
    done = subprocess.run(
        [ROOT / "scripts" / "setup"], cwd=ROOT, env=env, capture_output=True, text=True,
        timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    last = done.stdout.strip().splitlines()[-1]
    assert "'source .venv/bin/activate' puts ups on the PATH" in last, done.stdout
    version = subprocess.run(
        ["bash", "-c", "source .venv/bin/activate && ups --version"], cwd=ROOT, env=env,
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert version.returncode == 0 and version.stdout.startswith("ups "), version.stderr


@pytest.mark.netns  # the printed commands use the default port, 7411: in a namespace of our own
@pytest.mark.timeout(300)
def test_the_commands_the_demo_prints_to_try_next_work_as_typed_in_new_shells() -> None:
    private_network()
    env = new_shell_environment()
    demo = Proc(shell="scripts/demo", env=env, exact_env=True)
    code, out = demo.finish(timeout=240)
    assert code == 0, "".join(demo.stderr_lines)
    block = out.split("Try next (each in its own shell):\n", 1)[1].split("\nOn a real bus")[0]
    first, *commands = (line.split("#")[0].strip() for line in block.splitlines())
    assert first == "source .venv/bin/activate" and commands[0] == "ups broker", block
    shells: list[Proc] = []
    try:
        for command in commands:  # each in a new shell: first the line the demo says, then it
            shell = Proc(shell=f"{first} && exec {command}", env=env, exact_env=True)
            shells.append(shell)
            ready = READY.get(command.split()[1])
            if ready is not None:
                shell.wait_for_line(ready, timeout=60)
                continue
            code, printed = shell.finish(timeout=60)
            assert code == 0, f"{command}: {''.join(shell.stderr_lines)}"
            if command.startswith("ups pub"):
                sub = shells[commands.index("ups sub robot/speed --broker 127.0.0.1:7411")]
                sub.wait_for_stdout(5, timeout=60)
            if command.startswith("ups ls"):
                assert "robot/speed" in printed and "ups-sub" in printed, printed
        events = [line.split()[:2] for line in shells[1].stdout_lines]
        assert events == [["robot/speed", "0032"]] * 5, events
    finally:
        for shell in shells:
            shell.stop()
