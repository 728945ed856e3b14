"""A compiled copy of UPS for the benchmarks and the tests: ``build/compiled-<key>/`` holds
``ups/`` with the modules that ``UPS_COMPILE=1`` compiles (see setup.py) built beside their
sources, for ``PYTHONPATH``. Built once per source (the key hashes ``ups/``, the Python and
the mypy version); an older copy is removed when a new one is built.

    .venv/bin/python -m ups.benchmarks._compiled   # build if needed, print the directory
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
BUILD_TIMEOUT = 900.0  # seconds; about 30 s on a 2-core machine
_COPIED = ("setup.py", "pyproject.toml", "README.md")
#: the project's other packages, installed inside ``ups`` (the links ``ups/broker`` ->
#: ``../broker``, ...): not compiled; the copy links to the checkout's, and their modules stay
#: loaded when a process switches to the copy
LINKED = ("broker", "gateway", "jaus", "ros2", "ethercat", "examples", "benchmarks")


def unavailable() -> str | None:
    """Why the compiled copy cannot be built here, or None."""
    try:
        importlib.metadata.version("mypy")
    except importlib.metadata.PackageNotFoundError:
        return "mypy (mypyc) is not installed: scripts/setup --test"
    try:
        setuptools = importlib.metadata.version("setuptools")
    except importlib.metadata.PackageNotFoundError:
        return "setuptools is not installed: scripts/setup --test"
    if int(setuptools.split(".")[0]) < 77:  # pyproject.toml's license is an SPDX string
        return f"setuptools {setuptools} is older than 77: scripts/setup --test"
    if shutil.which(os.environ.get("CC", "cc")) is None:
        return "no C compiler (cc) on PATH"
    return None


def key() -> str:
    """What the copy is built from: every file of ``ups/``, the build files, the versions."""
    digest = hashlib.sha256(f"{sys.version}|{importlib.metadata.version('mypy')}".encode())
    for path in sorted((ROOT / "ups").rglob("*.py")):
        if path.relative_to(ROOT / "ups").parts[0] in LINKED:
            continue
        digest.update(str(path.relative_to(ROOT)).encode())
        digest.update(path.read_bytes())
    for name in _COPIED[:2]:
        digest.update((ROOT / name).read_bytes())
    return digest.hexdigest()[:16]


def build() -> Path:
    """The directory to put first on ``sys.path`` for the compiled UPS; built if it is not yet.
    Raises RuntimeError (with the compiler's last words) when the build fails."""
    why = unavailable()
    if why:
        raise RuntimeError(f"cannot build the compiled UPS: {why}")
    dest = ROOT / "build" / f"compiled-{key()}"
    if (dest / ".built").exists():
        return dest
    tmp = dest.with_name(f"{dest.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    skip = shutil.ignore_patterns("__pycache__", "*.so")
    top = str(ROOT / "ups")

    def ignore(folder: str, names: list[str]) -> set[str]:
        return set(skip(folder, names)) | (set(LINKED) if folder == top else set())

    shutil.copytree(ROOT / "ups", tmp / "ups", ignore=ignore)
    for name in LINKED:
        (tmp / "ups" / name).symlink_to(ROOT / name)
    for name in _COPIED:
        shutil.copy2(ROOT / name, tmp / name)
    env = dict(os.environ, UPS_COMPILE="1")
    done = subprocess.run(
        [sys.executable, "setup.py", "-q", "build_ext", "--inplace"],
        cwd=tmp, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
        timeout=BUILD_TIMEOUT,
    )  # fmt: skip
    if done.returncode != 0:
        shutil.rmtree(tmp, ignore_errors=True)
        tail = (done.stdout + done.stderr).strip().splitlines()[-15:]
        raise RuntimeError("building the compiled UPS failed:\n" + "\n".join(tail))
    shutil.rmtree(tmp / "build", ignore_errors=True)  # mypyc's C sources and objects
    (tmp / ".built").touch()
    for old in dest.parent.glob("compiled-*"):  # copies of older sources (not a build under way)
        if old not in (tmp, dest) and ".tmp" not in old.name:
            shutil.rmtree(old, ignore_errors=True)
    try:
        tmp.rename(dest)
    except OSError:  # built meanwhile by another process: theirs is the same
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def use(path: Path | str) -> None:
    """Make this process import the compiled copy at ``path`` (call it before UPS is used): any
    ``ups`` module imported already (a spawned child imports its parent's main module) is
    dropped first. Raises RuntimeError if the compiled modules are not what gets imported."""
    path = str(path)
    if sys.path[0] != path:
        for name in [n for n in sys.modules if n == "ups" or n.startswith("ups.")]:
            if name.split(".")[1:2] != [] and name.split(".")[1] in LINKED:
                continue  # not compiled: the module already loaded is the one to keep
            del sys.modules[name]
        sys.path.insert(0, path)
    import ups._tcplink

    if not (ups._tcplink.__file__ or "").endswith(".so"):
        raise RuntimeError(f"imported {ups._tcplink.__file__}, not the compiled UPS")


def import_ups(path: Path | str | None) -> ModuleType:
    """The ``ups`` package: the compiled copy at ``path`` (see :func:`use`), or, with None,
    the one installed."""
    if path is not None:
        use(path)
    import ups

    return ups


def compiled_modules(path: Path) -> list[str]:
    """The modules of the copy at ``path`` that are extension modules (``ups._tcplink``, ...)."""
    return sorted(f"ups.{p.name.split('.')[0]}" for p in (path / "ups").glob("*.so"))


if __name__ == "__main__":
    print(build())
