"""libups builds clean: gcc with -std=c99 -Wall -Wextra -Werror -pedantic -Wconversion
-Wsign-conversion in every configuration, gcc -fanalyzer and cppcheck (``make -C c check``); and
the SocketCAN examples build (``make -C c examples``; tests/socketcan runs them)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

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


def test_sizes_are_measured_and_the_minimal_node_fits_the_target() -> None:
    if shutil.which("arm-none-eabi-gcc") is None:
        pytest.fail("arm-none-eabi-gcc is missing: scripts/setup --test installs it")
    done = make("size")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    results = json.loads((ROOT / "c" / "build" / "size.json").read_text())
    assert {(r["cpu"], r["config"]) for r in results} >= {
        ("cortex-m0plus", "minimal"), ("cortex-m0plus", "full"), ("cortex-m4", "full"),
    }  # fmt: skip
    for r in results:
        assert r["flash"] > 1000 and r["ram"] >= r["node"] > 0 and 0 < r["stack"] < 1024
    (minimal,) = [r for r in results if (r["cpu"], r["config"]) == ("cortex-m0plus", "minimal")]
    assert minimal["flash"] <= 4096 and minimal["ram"] <= 256, minimal


def test_make_size_without_the_arm_toolchain_names_the_package(tmp_path: Path) -> None:
    """A PATH with make and python3 but no arm-none-eabi-gcc: one line, no traceback."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("make", "sh", "mkdir"):
        found = shutil.which(tool)
        assert found is not None
        (bin_dir / tool).symlink_to(found)
    (bin_dir / "python3").symlink_to(sys.executable)  # not a shim (pyenv's need bash)
    done = subprocess.run(
        ["make", "-C", str(ROOT / "c"), "size"], capture_output=True, text=True, timeout=60,
        check=False, env={"PATH": str(bin_dir)},
    )  # fmt: skip
    assert done.returncode != 0
    assert "apt-get install gcc-arm-none-eabi" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr
