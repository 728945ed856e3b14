#!/usr/bin/env python3
"""Measure libups on Cortex-M0+ and Cortex-M4 (``make -C c size``): flash, RAM and stack.

Each configuration is compiled with ``arm-none-eabi-gcc -Os`` (and -ffunction-sections), with
no flag that keeps gcc from calling memcpy or memset: the undefined symbols are checked to be
none, so the library calls no C library function as any build compiles it, and the figures are
its whole cost.

- flash: text + data of the library linked alone with -Wl,--gc-sections (as an application
  links it), every public function (ups_...) kept: what an application that calls them all
  pays; internal functions no public one reaches (in that configuration) are not counted;
- RAM: data + bss of the objects (none: the library has no variable of its own) plus one
  ups_node_t, the whole state, which the application places (the bss of a file defining one);
- stack: the worst case over every path of the call graph from each public function, from
  gcc's -fcallgraph-info=su (each function's own frame, from -fstack-usage, and its calls; the
  library has no recursion and no calls through pointers, so the bound is exact for its code).

Writes build/size.json: a list of {cpu, config, flash, ram, stack, deepest, node}.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
OUT = HERE / "build" / "size"
CC = "arm-none-eabi-gcc"
CPUS = {
    "cortex-m0plus": ["-mcpu=cortex-m0plus", "-mthumb"],
    "cortex-m4": ["-mcpu=cortex-m4", "-mthumb"],
}
CONFIGS = {
    "minimal": "-DUPS_CHANNELS=8 -DUPS_TX_DEPTH=4 -DUPS_DECLARATIONS=0 -DUPS_COUNTER_T=uint16_t",
    "minimal+declare": "-DUPS_CHANNELS=8 -DUPS_TX_DEPTH=4 -DUPS_DECLARATIONS=1 "
    "-DUPS_COUNTER_T=uint16_t",
    "default": "",
    "full": "-DUPS_CHANNELS=16 -DUPS_TX_DEPTH=16 -DUPS_WITH_TRANSFERS=1 -DUPS_WITH_FD=1 "
    "-DUPS_MAX_EVENT=1024 -DUPS_RX_TRANSFERS=4 -DUPS_DECLARATIONS=2 -DUPS_HEARD_BINDS=8",
}
ABOUT = {
    "minimal": "8 channels, events <= 8 B, classic CAN, TX queue 4, 16-bit counters",
    "minimal+declare": "the same with one real-time declaration",
    "default": "ups.h's defaults: 8 channels, TX queue 8, one declaration, 32-bit counters",
    "full": "16 channels, TX queue 16, transfers and CAN FD, events <= 1024 B, 4 transfers "
    "reassembled at once, 2 declarations, 8 Binds remembered (doubt)",
}
SOURCES = ("ups_util.c", "ups.c", "ups_join.c", "ups_bind.c", "ups_transfer.c")
TARGET = ("cortex-m0plus", "minimal", 4096, 256)  # the issue's: 4 KB flash, 256 B RAM
FLAGS = ["-Os", "-std=c99", "-ffunction-sections", "-fdata-sections", "-fstack-usage",
         "-fcallgraph-info=su"]  # fmt: skip


def run(*cmd: str, cwd: Path | None = None) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=cwd).stdout


def sizes(obj: Path) -> tuple[int, int, int]:
    """text, data, bss of an object file."""
    text, data, bss = run("arm-none-eabi-size", str(obj)).splitlines()[1].split()[:3]
    return int(text), int(data), int(bss)


def worst_stack(ci_files: list[Path]) -> tuple[int, str]:
    """The deepest stack of any public function (``ups_...``), and that path."""
    own: dict[str, int] = {}
    calls: dict[str, set[str]] = {}
    for ci in ci_files:
        text = ci.read_text()
        for title, label in re.findall(r'node: \{ title: "([^"]+)" label: "([^"]+)"', text):
            name = title.rsplit(":", 1)[-1]
            found = re.search(r"\\n(\d+) bytes", label)
            if found:
                own[name] = max(own.get(name, 0), int(found.group(1)))
        for src, dst in re.findall(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"', text):
            calls.setdefault(src.rsplit(":", 1)[-1], set()).add(dst.rsplit(":", 1)[-1])
    memo: dict[str, tuple[int, list[str]]] = {}

    def depth(fn: str, seen: tuple[str, ...]) -> tuple[int, list[str]]:
        if fn in seen:
            raise SystemExit(f"size.py: recursion through {fn}: no stack bound")
        if fn not in memo:
            if fn not in own and fn not in calls:
                raise SystemExit(f"size.py: a call to {fn}, outside the library")
            best = max(
                (depth(c, (*seen, fn)) for c in calls.get(fn, ())),
                default=(0, []),
                key=lambda d: d[0],
            )
            memo[fn] = (own.get(fn, 0) + best[0], [fn, *best[1]])
        return memo[fn]

    entries = [f for f in own if f.startswith("ups_") and not f.startswith("ups__")]
    stack, path = max((depth(f, ()) for f in entries), key=lambda d: d[0])
    return stack, " > ".join(path)


def measure(cpu: str, config: str) -> dict[str, Any]:
    out = OUT / cpu / config
    out.mkdir(parents=True, exist_ok=True)
    (out / "node.c").write_text('#include "ups.h"\nups_node_t node;\n')
    flags = [*CPUS[cpu], *FLAGS, *CONFIGS[config].split(), f"-I{HERE}"]
    objects = []
    for src in SOURCES:
        obj = out / src.replace(".c", ".o")
        run(CC, *flags, "-c", str(HERE / src), "-o", str(obj), cwd=out)
        objects.append(obj)
    defined = {line.split()[-1] for o in objects for line in
               run("arm-none-eabi-nm", "--defined-only", str(o)).splitlines()}  # fmt: skip
    needed = {line.split()[-1] for o in objects for line in
              run("arm-none-eabi-nm", "-u", str(o)).splitlines()} - defined  # fmt: skip
    if needed:
        raise SystemExit(f"size.py: {cpu} {config} needs {sorted(needed)} from outside")
    run(CC, *flags, "-fno-common", "-c", "node.c", "-o", "node.o", cwd=out)
    public = sorted(
        name for o in objects for line in
        run("arm-none-eabi-nm", "--defined-only", "-g", str(o)).splitlines()
        for kind, name in [line.split()[-2:]]
        if kind == "T" and name.startswith("ups_") and not name.startswith("ups__")
    )  # fmt: skip
    run(CC, *CPUS[cpu], "-nostdlib", "-Wl,--gc-sections", "-Wl,--entry=0",
        *(f"-Wl,--undefined={name}" for name in public), "-o", "libups.elf",
        *(str(o) for o in objects), cwd=out)  # fmt: skip
    text, data, _ = sizes(out / "libups.elf")
    flash = text + data
    ram = sum(d + b for _, d, b in (sizes(o) for o in objects))
    node = sizes(out / "node.o")[2]
    stack, deepest = worst_stack([o.with_suffix(".ci") for o in objects])
    return {"cpu": cpu, "config": config, "flash": flash, "ram": ram + node, "stack": stack,
            "deepest": deepest, "node": node, "about": ABOUT[config]}  # fmt: skip


def largest(cpu: str, config: str, count: int = 8) -> str:
    listing = run(
        "arm-none-eabi-nm", "--size-sort", "-S", "-t", "d", str(OUT / cpu / config / "libups.elf")
    )
    rows = [(int(size), name) for _, size, _, name in (r.split() for r in listing.splitlines())]
    rows.sort(reverse=True)
    return ", ".join(f"{name} {size}" for size, name in rows[:count])


def main() -> int:
    if shutil.which(CC) is None:
        print(f"make size: {CC} is not on PATH: install it (Debian: apt-get install "
              "gcc-arm-none-eabi)", file=sys.stderr)  # fmt: skip
        return 2
    results = [measure(cpu, config) for cpu in CPUS for config in CONFIGS]
    (HERE / "build" / "size.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"{'cpu':14} {'config':16} {'flash':>6} {'ram':>6} {'stack':>6}  (bytes)")
    for r in results:
        print(f"{r['cpu']:14} {r['config']:16} {r['flash']:6} {r['ram']:6} {r['stack']:6}")
    cpu, config, flash_max, ram_max = TARGET
    target = next(r for r in results if r["cpu"] == cpu and r["config"] == config)
    for name in (config, f"{config}+declare"):  # declarations are what every node does too
        r = next(r for r in results if r["cpu"] == cpu and r["config"] == name)
        verdict = "within" if r["flash"] <= flash_max and r["ram"] <= ram_max else "MISSES"
        print(f"target: {name} on {cpu} {verdict} {flash_max} B flash and {ram_max} B RAM "
              f"({r['flash']} B, {r['ram']} B)")  # fmt: skip
    print(f"largest functions ({config}, {cpu}): {largest(cpu, config)}")
    print(f"deepest stack ({config}, {cpu}): {target['deepest']}")
    print(f"written: {HERE / 'build' / 'size.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
