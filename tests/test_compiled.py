"""The compiled fast path (``UPS_COMPILE=1``, see setup.py) behaves as the pure Python it is
compiled from: the TCP/IP tests run again, in a process of their own, on the compiled build.

mypyc checks at run time what pure Python only states in hints (a list where a tuple was
declared is a TypeError there), and a compiled class has no per-instance attributes to patch;
these tests are what keeps the two builds one. The build is made once per source
(:mod:`benchmarks._compiled`); ``ups bench`` measures the same copy.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ups.benchmarks import _compiled

ROOT = Path(__file__).resolve().parents[1]
#: the tests of the compiled modules' behaviour: nodes, links, wire, bounds, loss, invariants
TCP_TESTS = (
    "tests/test_tcpwire.py",
    "tests/test_tcplink_queue.py",
    "tests/test_tcp_node.py",
    "tests/test_tcp_bounds.py",
    "tests/test_tcp_loss.py",
    "tests/test_tcp_invariants.py",
    "tests/test_fast_path.py",
    "tests/test_patterns.py",
)
RUN_TIMEOUT = 600.0


@pytest.fixture(scope="module")
def compiled() -> Path:
    why = _compiled.unavailable()
    if why and os.environ.get("UPS_REQUIRE_COMPILER") == "1":  # scripts/test, as root
        pytest.fail(f"{why}: scripts/setup --test installs gcc and the Python headers")
    if why:
        pytest.skip(why)
    return _compiled.build()


def test_the_build_compiles_every_module_it_lists(compiled: Path) -> None:
    import tomllib

    listed = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ups"]["compiled"]
    want = sorted("ups." + Path(name).stem for name in listed)
    assert _compiled.compiled_modules(compiled) == want


@pytest.mark.timeout(RUN_TIMEOUT + 30)
def test_the_tcp_tests_pass_on_the_compiled_build(compiled: Path) -> None:
    # ups is imported from the compiled copy before pytest puts the checkout first on sys.path
    # (for the tests package): every later ``import ups...`` finds the package loaded already.
    launch = (
        "import sys; sys.path.insert(0, sys.argv[1]); import ups._tcplink, pytest; "
        "sys.exit(pytest.main(sys.argv[2:]))"
    )
    env = dict(os.environ, UPS_EXPECT_COMPILED="1")
    done = subprocess.run(
        [sys.executable, "-c", launch, str(compiled), "-q", "-p", "no:cacheprovider", "-x",
         *TCP_TESTS],
        cwd=ROOT, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
        timeout=RUN_TIMEOUT,
    )  # fmt: skip
    tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-30:])
    assert done.returncode == 0, tail
    assert " passed" in tail and "compiled build" in tail, tail


@pytest.mark.timeout(RUN_TIMEOUT)
def test_pip_builds_a_compiled_wheel_that_runs(compiled: Path, tmp_path: Path) -> None:
    """The user's way, as the README has it: ``UPS_COMPILE=1 pip wheel .``, with pip's build
    isolation (it fetches setuptools and mypy for the build backend in ``_build/``). The wheel
    is for this interpreter, holds every listed module compiled, and passes the wire tests."""
    import tomllib
    import zipfile

    src = tmp_path / "src"  # what the wheel is made of, away from the checkout's build/
    shutil.copytree(ROOT / "ups", src / "ups", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    shutil.copytree(ROOT / "_build", src / "_build", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("setup.py", "pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    env = dict(os.environ, UPS_COMPILE="1")
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
    built = subprocess.run(
        [*pip, "wheel", "--no-deps", "-w", str(tmp_path / "wheel"), str(src)],
        env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=RUN_TIMEOUT,
    )  # fmt: skip
    assert built.returncode == 0, (built.stdout + built.stderr)[-3000:]
    assert "Warning" not in built.stderr, built.stderr[-3000:]  # e.g. a deprecated pyproject
    (wheel,) = (tmp_path / "wheel").glob("*.whl")
    tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
    assert f"-{tag}-{tag}-linux_" in wheel.name, wheel.name
    listed = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ups"]["compiled"]
    names = zipfile.ZipFile(wheel).namelist()
    for module in listed:
        stem = Path(module).stem
        assert any(n.startswith(f"ups/{stem}.cpython-") and n.endswith(".so") for n in names), (
            f"{module} is not compiled in {wheel.name}"
        )
    site = tmp_path / "site"
    installed = subprocess.run(
        [*pip, "install", "--no-deps", "--no-index", "--target", str(site), str(wheel)],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert installed.returncode == 0, (installed.stdout + installed.stderr)[-3000:]
    launch = (
        "import sys; sys.path.insert(0, sys.argv[1]); import ups._tcplink, pytest; "
        "sys.exit(pytest.main(sys.argv[2:]))"
    )
    done = subprocess.run(
        [sys.executable, "-c", launch, str(site), "-q", "-p", "no:cacheprovider",
         "tests/test_tcpwire.py"],
        cwd=ROOT, env=dict(os.environ, UPS_EXPECT_COMPILED="1"), stdin=subprocess.DEVNULL,
        capture_output=True, text=True, timeout=RUN_TIMEOUT,
    )  # fmt: skip
    tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-30:])
    assert done.returncode == 0 and "compiled build" in tail, tail
