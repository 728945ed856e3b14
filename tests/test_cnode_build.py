"""libups builds clean: gcc with -std=c99 -Wall -Wextra -Werror -pedantic -Wconversion
-Wsign-conversion in every configuration, gcc -fanalyzer and cppcheck (``make -C c check``); and
the SocketCAN examples build (``make -C c examples``; tests/socketcan runs them)."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from .procs import ROOT


def make(*targets: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["make", "-C", str(ROOT / "c"), *targets],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_make_check_is_clean() -> None:
    if shutil.which("cppcheck") is None:
        pytest.fail("cppcheck is missing: scripts/setup --test installs it")
    done = make("check")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "warning" not in done.stderr.lower()


def test_examples_build() -> None:
    done = make("examples")
    assert done.returncode == 0, done.stderr[-3000:]
    assert (ROOT / "c" / "build" / "ups-sensor").exists()
    assert (ROOT / "c" / "build" / "ups-actuator").exists()
