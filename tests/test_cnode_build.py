"""libups builds clean: gcc with -std=c99 -Wall -Wextra -Werror -pedantic -Wconversion
-Wsign-conversion in every configuration, gcc -fanalyzer and cppcheck (``make -C c check``); no
compiler makes a C library call of it at any optimisation; and the SocketCAN examples build
(``make -C c examples``; tests/socketcan runs them)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from .procs import ROOT

#: seconds a make of the C library may take: -fanalyzer, cppcheck and the sanitizer builds are
#: CPU-bound and take minutes on a machine other work keeps busy (pytest's 60 s would stop them)
MAKE_TIMEOUT = 300


def make(*targets: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["make", "-C", str(ROOT / "c"), *targets],
        capture_output=True,
        text=True,
        timeout=MAKE_TIMEOUT,
        check=False,
    )


@pytest.mark.timeout(MAKE_TIMEOUT + 30)
def test_make_check_is_clean() -> None:
    if shutil.which("cppcheck") is None:
        pytest.fail("cppcheck is missing: scripts/setup --test installs it")
    done = make("check")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "warning" not in done.stderr.lower()


@pytest.mark.timeout(MAKE_TIMEOUT + 30)
def test_examples_build() -> None:
    done = make("examples")
    assert done.returncode == 0, done.stderr[-3000:]
    assert (ROOT / "c" / "build" / "ups-sensor").exists()
    assert (ROOT / "c" / "build" / "ups-actuator").exists()
    assert (ROOT / "c" / "build" / "ups-broker").exists()  # libups and libups-ecb in one image


@pytest.mark.timeout(MAKE_TIMEOUT + 30)
def test_sizes_are_measured_and_the_minimal_node_fits_the_target() -> None:
    if shutil.which("arm-none-eabi-gcc") is None:
        pytest.fail("arm-none-eabi-gcc is missing: scripts/setup --test installs it")
    done = make("size")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    results = json.loads((ROOT / "c" / "build" / "size.json").read_text())
    assert {(r["cpu"], r["config"]) for r in results} >= {
        ("cortex-m0plus", "minimal"), ("cortex-m0plus", "full"), ("cortex-m4", "full"),
        ("cortex-m0plus", "ecb-small"), ("cortex-m0plus", "ecb-full"),
        ("cortex-m0plus", "node+ecb"), ("cortex-m4", "ecb-small"),
    }  # fmt: skip
    for r in results:
        assert r["flash"] > 1000 and r["ram"] >= r["node"] > 0
        # libups calls no libgcc helper either; the CAN-ECB's admission analysis takes more stack
        libups = r["library"] == "libups"
        assert 0 < r["stack"] < (1024 if libups else 2048) and (r["runtime"] == [] or not libups)
    (minimal,) = [r for r in results if (r["cpu"], r["config"]) == ("cortex-m0plus", "minimal")]
    assert minimal["flash"] <= 4096 and minimal["ram"] <= 256, minimal


# The library's sources, as c/Makefile lists them (SRC): every build of it here compiles these.
C_SOURCES = next(
    line.split(":=", 1)[1].split()
    for line in (ROOT / "c" / "Makefile").read_text().splitlines()
    if line.startswith("SRC :=")
)

CONFIGS = {
    "minimal": ["-DUPS_CHANNELS=8", "-DUPS_TX_DEPTH=4", "-DUPS_DECLARATIONS=0",
                "-DUPS_COUNTER_T=uint16_t"],
    "default": [],
    "full": ["-DUPS_CHANNELS=16", "-DUPS_TX_DEPTH=16", "-DUPS_WITH_TRANSFERS=1", "-DUPS_WITH_FD=1",
             "-DUPS_MAX_EVENT=1024", "-DUPS_RX_TRANSFERS=4", "-DUPS_DECLARATIONS=2",
             "-DUPS_HEARD_BINDS=8"],
}  # fmt: skip


@pytest.mark.parametrize("level", ["-Os", "-O2", "-O3"])
def test_no_compiler_makes_a_c_library_call_of_the_library(tmp_path: Path, level: str) -> None:
    """gcc turns a loop that stores contiguous bytes into a call of memset, memcpy or memmove
    unless told not to (-ffreestanding, -fno-tree-loop-distribute-patterns); libups' loops are
    written so that it cannot, and a -nostdlib link of it needs no flag. Every configuration, on
    Cortex-M0+ and Cortex-M4 and with the host's cc, with no such flag: the objects need nothing
    but each other."""
    if shutil.which("arm-none-eabi-gcc") is None:
        pytest.fail("arm-none-eabi-gcc is missing: scripts/setup --test installs it")
    compilers = {
        "cortex-m0plus": (
            ["arm-none-eabi-gcc", "-mcpu=cortex-m0plus", "-mthumb"],
            "arm-none-eabi-nm",
        ),
        "cortex-m4": (["arm-none-eabi-gcc", "-mcpu=cortex-m4", "-mthumb"], "arm-none-eabi-nm"),
        "host": (["cc"], "nm"),
    }
    sources = [str(ROOT / "c" / s) for s in C_SOURCES]

    def undefined(target: str, config: str) -> list[str]:
        """The symbols outside libups that its objects, built for ``target``, need."""
        cc, nm = compilers[target]
        out = tmp_path / target / config
        out.mkdir(parents=True)
        flags = CONFIGS[config]
        subprocess.run([*cc, level, "-std=c99", *flags, "-c", *sources], cwd=out, check=True)
        needed = set()
        for obj in out.glob("*.o"):
            listing = subprocess.run([nm, "-u", str(obj)], capture_output=True, text=True,
                                     check=True).stdout  # fmt: skip
            needed |= {line.split()[-1] for line in listing.splitlines() if line.strip()}
        return sorted(s for s in needed if not s.startswith("ups_"))

    # the builds are independent: one per core at a time (the other test worker mostly waits)
    builds = [(target, config) for target in compilers for config in CONFIGS]
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        found = dict(zip(builds, pool.map(lambda b: undefined(*b), builds), strict=True))
    calls = {f"{target} {config}": out for (target, config), out in found.items() if out}
    assert calls == {}


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
