#!/usr/bin/env python3
"""Measure libups and libups-ecb on Cortex-M0+ and Cortex-M4 (``make -C c size``): flash, RAM
and stack.

Each configuration is compiled with ``arm-none-eabi-gcc -Os`` (and -ffunction-sections), with
no flag that keeps gcc from calling memcpy or memset: the undefined symbols are checked to be
none but the compiler's own run-time helpers (libgcc's __aeabi_... and __gnu_...: division on
a core with no divide instruction, 64-bit multiplication, switch tables), so the library calls
no C library function as any build compiles it. libups needs none of them; those a build
needs are linked in from libgcc (-lgcc), listed in ``runtime`` and counted in its flash and
stack, so the figures are its whole cost.

- flash: text + data of the library linked alone with -Wl,--gc-sections (as an application
  links it), every public function (ups_... of libups, ups_ecb_... of libups-ecb) kept: what an
  application that calls them all pays; internal functions no public one reaches (in that
  configuration) are not counted;
- RAM: data + bss of the objects (none: the libraries have no variable of their own) plus the
  whole state the application places (the bss of a file defining it): one ups_node_t, one
  ups_ecb_t, or both for the node and the CAN-ECB in one image;
- stack: the worst case over every path of the call graph from each public function, from
  gcc's -fcallgraph-info=su (each function's own frame, from -fstack-usage, and its calls; the
  libraries have no recursion and no calls through pointers, so the bound is exact for their
  code); a libgcc helper's frame is what its disassembly pushes and takes off the stack pointer,
  summed over the function (a bound), and so are the helpers it calls. In one image the node
  and the CAN-ECB are called one after the other, from one context: the deeper of the two.

The CAN-ECB's sources and its two buses (ECB_SRC, ECB_SMALL, ECB_FULL) are read from the
Makefile, so that the figures are of what it builds.

Writes build/size.json: a list of {cpu, config, library, flash, ram, stack, deepest, node,
runtime, about} and for the CAN-ECB parts (what of ups_ecb_t each part's state takes);
``node`` is the size of the state (ups_node_t, ups_ecb_t or both), ``runtime`` the libgcc
helpers the build calls.
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
    "ecb-small": "the CAN-ECB of a small bus, with admission (Makefile ECB_SMALL: {}; "
    "ups_ecb.h's defaults for the rest)",
    "ecb-full": "the CAN-ECB of a full bus (Makefile ECB_FULL: {})",
    "node+ecb": "one image, node and broker: libups minimal + libups-ecb small ({})",
}  # {}: the Makefile's -D flags
SOURCES = ("ups_util.c", "ups.c", "ups_join.c", "ups_bind.c", "ups_transfer.c")
TARGETS = [  # (cpu, config, flash, RAM): the issues'
    ("cortex-m0plus", "minimal", 4096, 256),  # issue 31: 4 KB flash, 256 B RAM
    ("cortex-m0plus", "minimal+declare", 4096, 256),  # declarations are what every node does
    ("cortex-m0plus", "ecb-small", 10240, 2048),  # issue 40: 10 KB flash, 2 KB RAM
]
RUNTIME = ("__aeabi_", "__gnu_")  # the compiler's run-time helpers (libgcc), not the C library
FLAGS = ["-Os", "-std=c99", "-ffunction-sections", "-fdata-sections", "-fstack-usage",
         "-fcallgraph-info=su"]  # fmt: skip
PARTS = ("join", "bind", "elect", "counters")  # members of ups_ecb_t: the parts' state
NODE = ('#include "ups.h"\n', "ups_node_t node;\n")
ECB = ('#include "ups_ecb.h"\n', "ups_ecb_t ecb;\n")


def makefile_list(name: str) -> list[str]:
    """The words of ``NAME := ...`` in the Makefile (continued lines too)."""
    text = (HERE / "Makefile").read_text().replace("\\\n", " ")
    found = re.search(rf"^{re.escape(name)}\s*:=(.*)$", text, re.MULTILINE)
    if found is None:
        raise SystemExit(f"size.py: no {name} := in c/Makefile")
    return found.group(1).split()


def builds() -> dict[str, tuple[str, list[str], list[str], tuple[str, ...]]]:
    """config -> (library, sources, -D flags, the state's declaration lines)."""
    ecb = makefile_list("ECB_SRC")
    minimal = CONFIGS["minimal"].split()
    table = {c: ("libups", list(SOURCES), f.split(), NODE) for c, f in CONFIGS.items()}
    table["ecb-small"] = ("libups-ecb", ecb, makefile_list("ECB_SMALL"), ECB)
    table["ecb-full"] = ("libups-ecb", ecb, makefile_list("ECB_FULL"), ECB)
    table["node+ecb"] = ("libups + libups-ecb", [*SOURCES, *ecb],
                         [*minimal, *makefile_list("ECB_SMALL")], (*NODE, *ECB))  # fmt: skip
    return table


def run(*cmd: str, cwd: Path | None = None) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=cwd).stdout


def sizes(obj: Path) -> tuple[int, int, int]:
    """text, data, bss of an object file."""
    text, data, bss = run("arm-none-eabi-size", str(obj)).splitlines()[1].split()[:3]
    return int(text), int(data), int(bss)


def is_public(name: str) -> bool:
    """A function of the API: ups_... (libups) or ups_ecb_... (libups-ecb), not their internal
    ups__... and ups_ecb__... ones."""
    return name.startswith("ups_") and not name.startswith(("ups__", "ups_ecb__"))


def runtime_frames(elf: Path) -> tuple[dict[str, int], dict[str, set[str]]]:
    """From the disassembly of a linked image: the stack of each libgcc function (``__...``:
    what it pushes and takes off sp, summed over the function, a bound) and its calls, and the
    calls of every function to them (a switch table's helper is called from code that
    -fcallgraph-info does not see). Every name of an address (aliases) gets its figures."""
    names: dict[int, list[str]] = {}
    for line in run("arm-none-eabi-nm", str(elf)).splitlines():
        address, kind, name = line.split()
        if kind in "TtW":
            names.setdefault(int(address, 16), []).append(name)
    frame: dict[int, int] = {}
    called: dict[int, set[int]] = {}
    at = -1
    for line in run("arm-none-eabi-objdump", "-d", str(elf)).splitlines():
        head = re.match(r"([0-9a-f]+) <[^>]+>:$", line)
        if head:
            at = int(head.group(1), 16)
            frame[at], called[at] = 0, set()
            continue
        if at < 0:
            continue
        push = re.search(r"\t(?:push(?:\.w)?|stmdb(?:\.w)?\s+sp!,)\s+\{([^}]*)\}", line)
        if push:
            for reg in push.group(1).split(","):
                first, _, last = reg.strip().partition("-")
                frame[at] += 4 * (int(last[1:]) - int(first[1:]) + 1 if last else 1)
        sub = re.search(r"\tsub(?:\.w)?\s+sp, (?:sp, )?#(\d+)", line)
        if sub:
            frame[at] += int(sub.group(1))
        call = re.search(r"\tblx?\s+([0-9a-f]+) <", line)
        if call:
            target = int(call.group(1), 16)
            start = max((a for a in frame if a <= target), default=target)
            called[at].add(target if target in names else start)
    runtime = {a for a, n in names.items() if any(x.startswith("__") for x in n)}
    own: dict[str, int] = {}
    calls: dict[str, set[str]] = {}
    for address, targets in called.items():
        helpers = {n for t in targets & runtime for n in names.get(t, [])}
        for name in names.get(address, []):
            if address in runtime:
                own[name] = frame[address]
                calls[name] = {n for t in targets for n in names.get(t, [])}
            elif helpers:
                calls[name] = helpers
    return own, calls


def worst_stack(
    ci_files: list[Path], entries: set[str], elf: Path | None = None
) -> tuple[int, str]:
    """The deepest stack of any of @p entries (the public functions), and that path; with
    @p elf, the libgcc helpers it links (runtime_frames) are part of the graph."""
    own: dict[str, int] = {}
    calls: dict[str, set[str]] = {}
    for ci in ci_files:  # a file's static functions are "FILE:NAME", so that no two meet
        text = ci.read_text()
        for title, label in re.findall(r'node: \{ title: "([^"]+)" label: "([^"]+)"', text):
            found = re.search(r"\\n(\d+) bytes", label)
            if found:
                own[title] = max(own.get(title, 0), int(found.group(1)))
        for src, dst in re.findall(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"', text):
            if not dst.startswith(RUNTIME):  # gcc may name a helper it then does not call
                calls.setdefault(src, set()).add(dst)
    if elf is not None:  # the helpers the code calls, from its disassembly
        helper_own, helper_calls = runtime_frames(elf)
        for name, targets in helper_calls.items():  # the disassembly names a static bare
            callers = [k for k in own if k == name or k.endswith(f":{name}")]
            for caller in callers if name not in helper_own else [name]:
                calls.setdefault(caller, set()).update(targets)
        own.update(helper_own)
    memo: dict[str, tuple[int, list[str]]] = {}

    def depth(fn: str, seen: tuple[str, ...]) -> tuple[int, list[str]]:
        if fn in seen:
            raise SystemExit(f"size.py: recursion through {bare(fn)}: no stack bound")
        if fn not in memo:
            if fn not in own and fn not in calls:
                raise SystemExit(f"size.py: a call to {bare(fn)}, outside the library")
            best = max(
                (depth(c, (*seen, fn)) for c in calls.get(fn, ())),
                default=(0, []),
                key=lambda d: d[0],
            )
            memo[fn] = (own.get(fn, 0) + best[0], [fn, *best[1]])
        return memo[fn]

    stack, path = max((depth(f, ()) for f in sorted(entries & set(own))), key=lambda d: d[0])
    return stack, " > ".join(bare(fn) for fn in path)


def bare(fn: str) -> str:
    """A function's name without the file of a static one."""
    return fn.rsplit(":", 1)[-1]


def measure(cpu: str, config: str) -> dict[str, Any]:
    library, sources, defines, state = builds()[config]
    out = OUT / cpu / config
    out.mkdir(parents=True, exist_ok=True)
    (out / "state.c").write_text("".join(sorted(state, key=lambda s: not s.startswith("#"))))
    flags = [*CPUS[cpu], *FLAGS, *defines, f"-I{HERE}"]
    objects = []
    for src in sources:
        obj = out / src.replace(".c", ".o")
        run(CC, *flags, "-c", str(HERE / src), "-o", str(obj), cwd=out)
        objects.append(obj)
    defined = {line.split()[-1] for o in objects for line in
               run("arm-none-eabi-nm", "--defined-only", str(o)).splitlines()}  # fmt: skip
    undefined = {o.name: {line.split()[-1] for line in
                          run("arm-none-eabi-nm", "-u", str(o)).splitlines()} - defined
                 for o in objects}  # fmt: skip
    needed = set().union(*undefined.values())
    outside = {o: sorted(n for n in u if not n.startswith(RUNTIME)) for o, u in undefined.items()}
    if any(outside.values()):
        calls = "; ".join(f"{o}: {' '.join(n)}" for o, n in outside.items() if n)
        raise SystemExit(f"size.py: {cpu} {config} calls functions from outside the library "
                         f"({calls}): gcc -Os makes calls of memcpy, memmove and memset of "
                         "struct assignments and copy loops (use the byte helpers)")  # fmt: skip
    run(CC, *flags, "-fno-common", "-c", "state.c", "-o", "state.o", cwd=out)
    public = sorted(
        name for o in objects for line in
        run("arm-none-eabi-nm", "--defined-only", "-g", str(o)).splitlines()
        for kind, name in [line.split()[-2:]]
        if kind == "T" and is_public(name)
    )  # fmt: skip
    run(CC, *CPUS[cpu], "-nostdlib", "-Wl,--gc-sections", "-Wl,--entry=0",
        *(f"-Wl,--undefined={name}" for name in public), "-o", "lib.elf",
        *(str(o) for o in objects), *(["-lgcc"] if needed else []), cwd=out)  # fmt: skip
    text, data, _ = sizes(out / "lib.elf")
    ram = sum(d + b for _, d, b in (sizes(o) for o in objects))
    node = sizes(out / "state.o")[2]
    stack, deepest = worst_stack([o.with_suffix(".ci") for o in objects], set(public),
                                 out / "lib.elf")  # fmt: skip
    macros = " ".join(d.removeprefix("-D") for d in defines)
    result = {"cpu": cpu, "config": config, "library": library, "flash": text + data,
              "ram": ram + node, "stack": stack, "deepest": deepest, "node": node,
              "runtime": sorted(needed), "about": ABOUT[config].format(macros)}  # fmt: skip
    if state == ECB:
        result["parts"] = parts(out, flags)
    return result


def parts(out: Path, flags: list[str]) -> dict[str, int]:
    """Bytes of ups_ecb_t by part: the state of ups_ecb_join.c, ups_ecb_bind.c and
    ups_ecb_elect.c, the counters, and the rest (ups_ecb.c's own: the TX queue, the echoes,
    the configuration, its timers)."""
    lines = [f"char part_{name}[sizeof(((ups_ecb_t *)0)->{name})];\n" for name in PARTS]
    (out / "parts.c").write_text(ECB[0] + "".join(lines))
    run(CC, *flags, "-fno-common", "-c", "parts.c", "-o", "parts.o", cwd=out)
    found = {}
    for line in run("arm-none-eabi-nm", "-S", "-t", "d", str(out / "parts.o")).splitlines():
        _, size, _, name = line.split()
        found[name.removeprefix("part_")] = int(size)
    shares = {name: found[name] for name in PARTS}
    return {**shares, "core": sizes(out / "state.o")[2] - sum(shares.values())}


def largest(cpu: str, config: str, count: int = 8) -> str:
    listing = run("arm-none-eabi-nm", "--size-sort", "-S", "-t", "d",
                  str(OUT / cpu / config / "lib.elf"))  # fmt: skip
    rows = [(int(size), name) for _, size, _, name in (r.split() for r in listing.splitlines())]
    rows.sort(reverse=True)
    return ", ".join(f"{name} {size}" for size, name in rows[:count])


def main() -> int:
    if shutil.which(CC) is None:
        print(f"make size: {CC} is not on PATH: install it (Debian: apt-get install "
              "gcc-arm-none-eabi)", file=sys.stderr)  # fmt: skip
        return 2
    results = [measure(cpu, config) for cpu in CPUS for config in builds()]
    (HERE / "build" / "size.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"{'cpu':14} {'config':16} {'flash':>6} {'ram':>6} {'stack':>6}  (bytes)")
    for r in results:
        print(f"{r['cpu']:14} {r['config']:16} {r['flash']:6} {r['ram']:6} {r['stack']:6}")
    for cpu, config, flash_max, ram_max in TARGETS:
        r = next(r for r in results if r["cpu"] == cpu and r["config"] == config)
        verdict = "within" if r["flash"] <= flash_max and r["ram"] <= ram_max else "MISSES"
        print(f"target: {config} on {cpu} {verdict} {flash_max} B flash and {ram_max} B RAM "
              f"({r['flash']} B, {r['ram']} B)")  # fmt: skip
    for r in results:
        if "parts" in r:
            shares = ", ".join(f"{name} {size}" for name, size in r["parts"].items())
            print(f"ups_ecb_t ({r['config']}, {r['cpu']}): {r['node']} B: {shares}")
    for r in results:
        if r["runtime"]:
            print(f"libgcc helpers ({r['config']}, {r['cpu']}): {' '.join(r['runtime'])}")
    for config in ("minimal", "ecb-small"):
        deepest = next(r["deepest"] for r in results
                       if (r["cpu"], r["config"]) == ("cortex-m0plus", config))  # fmt: skip
        print(f"largest functions ({config}, cortex-m0plus): {largest('cortex-m0plus', config)}")
        print(f"deepest stack ({config}, cortex-m0plus): {deepest}")
    print(f"written: {HERE / 'build' / 'size.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
