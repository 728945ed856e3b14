"""Optional parts that are not installed fail in one line that says what to install.

A real virtual environment without the extras: the checkout installed into it as a user's
editable install (``pip install --no-deps -e``), beside only the base dependencies (python-can,
msgpack, cryptography and what they need, taken from this environment), so ``zenoh``, ``rich``,
``aiohttp`` and ``cantools`` are really absent. Each command runs there as a user types it.
(A wheel installed from PyPI's way says ``pip install 'ups-pubsub[zenoh]'``: tests/test_wheel.py.)
"""

from __future__ import annotations

import importlib.metadata
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from .procs import ROOT, Proc

BASE = ("python-can", "msgpack", "cryptography")
#: what a virtual environment has before anything is installed into it, and what builds UPS
TOOLS = ("pip", "setuptools")
#: an error message that names a Python class ("ModuleNotFoundError", "ZError", ...)
CLASS_NAME = re.compile(r"\b[A-Z][a-zA-Z]*(Error|Exception)\b")


def link_distributions(names: tuple[str, ...], site: Path) -> set[str]:
    """Make the distributions ``names`` and what they require importable in ``site``, by
    linking their files from this environment; returns the distributions linked."""
    done: set[str] = set()
    todo = list(names)
    while todo:
        dist = importlib.metadata.distribution(todo.pop())
        key = dist.metadata["Name"].lower()
        if key in done:
            continue
        done.add(key)
        for text in dist.requires or ():
            req = Requirement(text)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                todo.append(req.name)
        tops = {Path(str(f)).parts[0] for f in dist.files or ()}
        for top in tops - {"..", "__pycache__"}:
            target = site / top
            if not target.exists():
                target.symlink_to(Path(str(dist.locate_file(top))))
    return done


@pytest.fixture(scope="module")
def bare(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A virtual environment with the checkout installed editable and no extra; its bin/."""
    env = tmp_path_factory.mktemp("bare") / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", env], check=True, timeout=120)
    (site,) = (env / "lib").glob("python3*/site-packages")
    linked = link_distributions((*BASE, *TOOLS), site)
    assert not {"eclipse-zenoh", "rich", "aiohttp", "cantools"} & linked
    subprocess.run(
        [env / "bin" / "python", "-m", "pip", "install", "-q", "--no-deps", "--no-index",
         "--no-build-isolation", "-e", ROOT],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    return env / "bin"


def user_env() -> dict[str, str]:
    """A user's environment: no UPS settings, no other Python's paths."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("UPS_", "PYTHON", "VIRTUAL"))}


def run(bin_dir: Path, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [bin_dir / "ups", *args], capture_output=True, text=True, cwd=cwd, env=user_env(),
        timeout=60, check=False,
    )  # fmt: skip


ZENOH = "tcp/127.0.0.1:1"


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    ("args", "extra"),
    [
        (["sub", "robot/speed", "--zenoh", ZENOH], "zenoh"),
        (["pub", "robot/speed", "01", "--zenoh", ZENOH], "zenoh"),
        (["status", "--zenoh", ZENOH], "zenoh"),
        (["gateway", "--can", "virtual:x", "--zenoh", ZENOH], "zenoh"),
        (["zenoh-router"], "zenoh"),
        (["ls", "--zenoh", ZENOH], "zenoh"),
        (["monitor", "--zenoh", ZENOH, "--plain"], "zenoh"),
        (["console", "--broker", "127.0.0.1:1"], "tools"),
        (["dbc", "-o", "robot.dbc", "--recording", "no.blf"], "tools"),
        (["ros2", "check", "examples/robot.ros2.toml"], "ros2"),
        (["ros2", "--map", "examples/robot.ros2.toml", "--can", "virtual:x"], "ros2"),
        (["ethercat", "scan", "--ifname", "lo"], "ethercat"),
    ],
)
def test_a_missing_extra_is_one_line_naming_what_to_install(
    bare: Path, args: list[str], extra: str
) -> None:
    done = run(bare, *args)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and not CLASS_NAME.search(done.stderr), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith(f"ups {args[0]}: ")
    python = bare / "python"  # outside the checkout, and without a pip script: python -m pip
    assert line.endswith(f"{python} -m pip install -e '.[{extra}]'"), line


def test_elsewhere_the_hint_names_the_checkout_and_the_library_says_it_too(
    bare: Path, tmp_path: Path
) -> None:
    done = run(bare, "sub", "x", "--zenoh", ZENOH, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip().endswith(f"{bare / 'python'} -m pip install -e '{ROOT}[zenoh]'")
    script = "import asyncio, ups\nasyncio.run(ups.Node(zenoh='tcp/127.0.0.1:1').start())"
    api = subprocess.run(
        [bare / "python", "-c", script], capture_output=True, text=True, timeout=60, check=False
    )
    assert "ConfigError: Zenoh is not installed (eclipse-zenoh)" in api.stderr, api.stderr


def test_without_the_extras_the_rest_works(bare: Path) -> None:
    env, ups = user_env(), bare / "ups"
    with Proc(shell=f"exec {ups} broker --listen 127.0.0.1:0 --recovery 0", env=env,
              exact_env=True) as broker:  # fmt: skip
        found = re.search(r"TCP-ECB on (127\.0\.0\.1:\d+)", broker.wait_for_line("TCP-ECB on"))
        assert found is not None
        address = found.group(1)
        with Proc(shell=f"exec {ups} sub robot/speed --broker {address} --count 1", env=env,
                  exact_env=True) as sub:  # fmt: skip
            sub.wait_for_line("subscribed to robot/speed")
            assert run(bare, "pub", "robot/speed", "0032", "--broker", address).returncode == 0
            code, out = sub.finish()
    assert code == 0 and out.startswith("robot/speed  0032"), sub.stderr_lines
