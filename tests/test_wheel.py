"""What ``pip install`` puts in site-packages: only names of our own (``ups``, ``upscli``), with
the daemons, the demo and the benchmarks inside ``ups``, and the demo runs from there.

A real wheel, built from this checkout, installed into a clean virtual environment (no
editable paths, no checkout on ``sys.path``: the commands run in an empty directory).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from .procs import ROOT

#: what the wheel may add at the top of site-packages (besides its .dist-info)
OUR_NAMES = {"ups", "upscli"}


def sh(*args: str | Path, cwd: Path | None = None) -> str:
    """Run a command to its end (at most 10 min); its output, stdout then stderr."""
    done = subprocess.run(
        [str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=600, check=False
    )
    assert done.returncode == 0, f"{args}: {done.stdout}{done.stderr}"
    return done.stdout + done.stderr


@pytest.mark.timeout(900)  # a wheel, a virtual environment and its packages, the demo
def test_the_wheel_installs_only_our_names_and_the_demo_runs_from_it(tmp_path: Path) -> None:
    wheels, env, elsewhere = tmp_path / "wheels", tmp_path / "venv", tmp_path / "elsewhere"
    elsewhere.mkdir()
    sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", wheels, ROOT)
    (wheel,) = wheels.glob("ups_pubsub-*.whl")
    sh(sys.executable, "-m", "venv", env)
    python, ups = env / "bin" / "python", env / "bin" / "ups"
    sh(python, "-m", "pip", "install", "-q", wheel)
    files = (
        "import importlib.metadata as m; "
        "print(*{str(f).split('/')[0] for f in m.files('ups-pubsub')})"
    )
    listing = sh(python, "-c", files, cwd=elsewhere).split()
    top = {name for name in listing if not name.endswith(".dist-info") and name != ".."}
    assert top == OUR_NAMES, listing  # ".." is bin/ups, the console script
    assert "everything arrived" in sh(ups, "demo", cwd=elsewhere)
    assert "usage: ups bench" in sh(ups, "bench", "--help", cwd=elsewhere)
    without = subprocess.run(  # installed without its extras: a missing one says what to do
        [ups, "sub", "x", "--zenoh", "tcp/127.0.0.1:1"], cwd=elsewhere, capture_output=True,
        text=True, timeout=60, check=False,
    )  # fmt: skip
    assert without.returncode == 2, without.stderr
    assert without.stderr.strip().endswith("pip install 'ups-pubsub[zenoh]'"), without.stderr
    sh(python, "-c", "import ups.broker, ups.gateway, ups.jaus, ups.ethercat, ups.examples, "
       "ups.benchmarks", cwd=elsewhere)  # fmt: skip
