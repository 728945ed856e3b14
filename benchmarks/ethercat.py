"""Paper 000's EtherCAT side on today's machine: ``ups ethercat`` against the tests' slave
emulator (tests/ecat, so: from a checkout) across a veth pair, inside a private namespace.

1. The cycle: ``ups ethercat --cycle MS`` runs ``--seconds`` against the two slaves of
   examples/robot.ethercat.toml, and then, as the peer, a bare pysoem loop (the same master
   library, the same period and sleep, no UPS) as long: cycles, late cycles (one started more
   than half a period after its time), lost frames and wrong working counters of each, and the
   ratio of their late cycles.
2. The paths, one at a time, ``--gap`` ms apart, one clock (this process's), in one run with a
   CAN-ECB on python-can's udp_multicast:

   - ``ecat_to_can``: a slave's input changes (the emulator's control socket) until the UPS
     CAN node here has the event (robot/distance);
   - ``can_to_ecat``: a UPS CAN event (robot/max-speed) until the slave's application has
     the output bytes (the emulator prints them);
   - ``jaus_to_ecat``: a JAUS Set Wrench Effort (JUDP, to ``ups jaus`` on the same CAN bus,
     examples/robot.jaus.toml) until the drive has the bytes: paper 000's JEBridge path;
   - ``can_to_can``: a UPS CAN event from one node to another, in the same run (reference).

    scripts/netns-run .venv/bin/python -m ups.benchmarks.ethercat [--cycle MS] [--seconds S]
        [--messages N] [--gap MS] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import queue
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

from ups.benchmarks._procs import ROOT, Child
from ups.benchmarks.jaus_paper000 import summary_ms
from ups.benchmarks.table5 import check_private_namespace, free_udp_port, ups_argv

SLAVES = (
    "vendor=0x2,product=0x7d23052,revision=0x00110000,name=EL-test-io,outputs=4,inputs=4",
    "vendor=0x5a5,product=0x1234,revision=3,name=UPS drive,outputs=2,inputs=6",
)
EXAMPLES = ROOT / "examples"
TIMEOUT = 1.0  #: s: a sample not through by then is lost


@contextlib.contextmanager
def veth() -> Iterator[tuple[str, str]]:
    """A veth pair here (in the private namespace): (the master's end, the slaves' end)."""
    tag = os.getpid() % 100000
    master, wire = f"ebm{tag}", f"ebs{tag}"
    subprocess.run(["ip", "link", "add", master, "type", "veth", "peer", "name", wire], check=True)
    try:
        for end in (master, wire):
            subprocess.run(["ip", "link", "set", end, "up"], check=True)
        yield master, wire
    finally:
        subprocess.run(["ip", "link", "del", master], check=False, capture_output=True)


class Emulator:
    """The tests' slaves on ``wire``: their output lines stamped as read, their inputs set."""

    def __init__(self, wire: str, tmp: Path) -> None:
        if not (ROOT / "tests" / "ecat").is_dir():
            sys.exit("the EtherCAT benchmark needs the tests' slave emulator: run it in a checkout")
        self.control = str(tmp / "ctl")
        argv = [sys.executable, "-m", "tests.ecat", "--ifname", wire, "--control", self.control]
        for slave in SLAVES:
            argv += ["--slave", slave]
        self.popen = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, text=True)
        self.lines: queue.Queue[tuple[int, str]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        self.wait(r"^ready ", 20)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(tmp / "me"))
        self.sock.settimeout(5)

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.put((time.perf_counter_ns(), line.strip()))

    def wait(self, pattern: str, timeout: float = TIMEOUT) -> int:
        """When (perf_counter_ns) a line matching ``pattern`` came; TimeoutError if none."""
        deadline = time.monotonic() + timeout
        regex = re.compile(pattern)
        while (left := deadline - time.monotonic()) > 0:
            try:
                when, line = self.lines.get(timeout=left)
            except queue.Empty:
                break
            if regex.search(line):
                return when
        raise TimeoutError(pattern)

    def inputs(self, position: int, data: bytes) -> None:
        self.sock.sendto(f"inputs {position} {data.hex()}".encode(), self.control)
        if self.sock.recv(100) != b"ok":
            raise RuntimeError("the emulator refused the inputs")

    def close(self) -> None:
        self.sock.close()
        self.popen.terminate()
        self.popen.wait(10)


# --- 1. the cycle ----------------------------------------------------------------------------


def cycle_part(master: str, wire: str, tmp: Path, args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    emulator = Emulator(wire, tmp)
    broker = Child(ups_argv("broker", "--listen", "127.0.0.1:0"), "ups broker")
    try:
        address = broker.wait_stderr(r"TCP-ECB on (\S+:\d+)").group(1)
        ecat = Child(ups_argv("ethercat", "--ifname", master, "--map",
                              str(EXAMPLES / "robot.ethercat.toml"), "--broker", address,
                              "--cycle", str(args.cycle)), "ups ethercat")  # fmt: skip
        try:
            node = ecat.wait_stderr(r"ups status (\S+)").group(1)
            before = _counters(node)
            time.sleep(args.seconds)  # the run: the master cycles meanwhile
            after = _counters(node)
            out["ups"] = {k: after[k] - before[k] for k in after}
        finally:
            ecat.stop()
        bare = subprocess.run([sys.executable, "-m", "ups.benchmarks.ethercat", "--bare", master,
                               str(args.cycle), str(args.seconds)], capture_output=True,
                              text=True, check=True, timeout=args.seconds + 60)  # fmt: skip
        out["pysoem"] = json.loads(bare.stdout.splitlines()[-1])
    finally:
        broker.stop()
        emulator.close()
    for row in out.values():
        row["late_percent"] = 100 * row["late"] / max(1, row["cycles"])
    out["late_ratio"] = out["ups"]["late"] / max(1, out["pysoem"]["late"])
    return out


def _counters(node: str) -> dict[str, int]:
    """The cycle's counters of ``ups ethercat`` (``ups status`` of its TCP node)."""
    status = subprocess.run(ups_argv("status", node, "--json"), capture_output=True, text=True,
                            check=True, timeout=30)  # fmt: skip
    seen = json.loads(status.stdout)["ethercat"]
    return {k: int(seen[k]) for k in ("cycles", "late", "lost", "wkc_errors")}


def bare_loop(ifname: str, cycle_ms: float, seconds: float) -> dict[str, int]:
    """The peer: pysoem's own cycle (send, receive, check, sleep), no UPS."""
    import pysoem

    master = pysoem.Master()
    master.open(ifname)
    try:
        master.config_init()
        master.config_map()
        master.state_check(pysoem.SAFEOP_STATE, 3_000_000)
        master.state = pysoem.OP_STATE
        master.write_state()
        for _ in range(3):
            master.send_processdata()
            master.receive_processdata(2000)
        master.state_check(pysoem.OP_STATE, 3_000_000)
        master.always_release_gil = True
        period, expected = cycle_ms / 1000, master.expected_wkc
        timeout = max(200, int(period * 1e6))
        counts = dict.fromkeys(("cycles", "late", "lost", "wkc_errors"), 0)
        due = time.monotonic()
        end = due + seconds
        while due < end:
            master.send_processdata()
            wkc = master.receive_processdata(timeout)
            counts["cycles"] += 1
            if wkc <= 0:
                counts["lost"] += 1
            elif wkc != expected:
                counts["wkc_errors"] += 1
            due += period
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -period / 2:
                counts["late"] += 1
                due = time.monotonic()
        return counts
    finally:
        master.state = pysoem.INIT_STATE
        master.write_state()
        master.close()


# --- 2. the paths ----------------------------------------------------------------------------


async def timed(one: Callable[[int], Awaitable[float]], count: int, gap: float) -> dict[str, Any]:
    samples, lost = [], 0
    for i in range(count):
        await asyncio.sleep(gap)
        try:
            samples.append(await one(i))
        except TimeoutError:
            lost += 1
    return {"n": len(samples), "lost": lost, "one_way_ms": summary_ms(samples)}


async def paths_part(master: str, wire: str, tmp: Path, args: argparse.Namespace) -> dict[str, Any]:
    from ups import Node
    from ups.benchmarks._jaus_ocu import Ocu
    from ups.benchmarks.jaus_paper000 import _take_control
    from ups.jaus import Resume, SetWrenchEffort

    bus = f"udp_multicast:239.74.163.4,port={free_udp_port()}"
    emulator = Emulator(wire, tmp)
    children = []
    try:
        ecb = Child(ups_argv("can-broker", "--can", bus, "--db", str(tmp / "ecb.db")), "ecb")
        children.append(ecb)
        ecb.wait_stderr("CAN-ECB on")
        ecat = Child(ups_argv("ethercat", "--ifname", master, "--map",
                              str(EXAMPLES / "robot.ethercat.toml"), "--can", bus, "--cycle",
                              str(args.cycle)), "ups ethercat")  # fmt: skip
        children.append(ecat)
        ecat.wait_stderr("master of 2 slave")
        jaus = Child(
            ups_argv(
                "jaus",
                "--listen",
                "127.0.0.1:0",
                "--id",
                "1.1.1",
                "--map",
                str(EXAMPLES / "robot.jaus.toml"),
                "--can",
                bus,
            ),
            "ups jaus",
        )
        children.append(jaus)  # fmt: skip
        found = jaus.wait_stderr(r"JAUS component \S+ on ([\d.]+):(\d+)")
        async with Node(can=bus, join_timeout=30) as node, Node(can=bus, join_timeout=30) as peer:
            arrived: asyncio.Queue[tuple[int, bytes]] = asyncio.Queue()

            def stamp(msg: Any) -> None:
                arrived.put_nowait((time.perf_counter_ns(), msg.data))

            await node.subscribe("robot/distance", callback=stamp)
            await peer.subscribe("bench/ref", callback=stamp)
            await node.advertise("robot/max-speed")
            await node.advertise("bench/ref")

            async def arrival(data: bytes) -> int:
                while True:
                    when, got = await asyncio.wait_for(arrived.get(), TIMEOUT)
                    if got == data:
                        return when

            async def ecat_to_can(i: int) -> float:
                value = 1 + i % 60000
                start = time.perf_counter_ns()
                emulator.inputs(1, struct.pack("<H", value) + bytes(2))
                return (await arrival(struct.pack(">H", value)) - start) / 1000

            async def can_to_ecat(i: int) -> float:
                limit = 1 + i % 3000
                start = time.perf_counter_ns()
                await node.publish("robot/max-speed", struct.pack(">h", limit))
                line = f"^outputs 2 {struct.pack('<h', limit * 10).hex()}$"
                return (await asyncio.to_thread(emulator.wait, line) - start) / 1000

            ocu = Ocu((found.group(1), int(found.group(2))), (1, 1, 1))

            async def jaus_to_ecat(i: int) -> float:
                percent = 1 + i % 90
                start = time.perf_counter_ns()
                ocu.send(SetWrenchEffort(propulsive_linear_x=float(percent)))
                line = f"^outputs 2 {struct.pack('<h', percent * 20).hex()}$"
                return (await asyncio.to_thread(emulator.wait, line) - start) / 1000

            async def can_to_can(i: int) -> float:
                data = i.to_bytes(4, "big")
                start = time.perf_counter_ns()
                await node.publish("bench/ref", data)
                return (await arrival(data) - start) / 1000

            paths = {}
            for name, one in (
                ("ecat_to_can", ecat_to_can),
                ("can_to_ecat", can_to_ecat),
                ("jaus_to_ecat", jaus_to_ecat),
                ("can_to_can", can_to_can),
            ):
                if name == "jaus_to_ecat":  # control lapses after 5 s of silence: take it now
                    await _take_control(ocu)
                    ocu.send(Resume())  # STANDBY -> READY: commands are carried out
                paths[name] = await timed(one, args.messages, args.gap / 1000)  # fmt: skip
                print(f"{name}: {_mean(paths[name])} ms", file=sys.stderr)
            ocu.close()
            return paths
    finally:
        for child in reversed(children):
            child.stop()
        emulator.close()


def _mean(row: dict[str, Any]) -> str:
    return f"{row['one_way_ms']['mean']:.3f}" if row["one_way_ms"] else "-"


PATHS = {
    "ecat_to_can": "EtherCAT input -> UPS CAN subscriber",
    "can_to_ecat": "UPS CAN event -> EtherCAT output",
    "jaus_to_ecat": "JAUS Set Wrench Effort -> UPS CAN -> EtherCAT output",
    "can_to_can": "UPS CAN node -> UPS CAN node (reference)",
}


def tables(doc: dict[str, Any]) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows): the cycle beside bare pysoem, then the paths."""
    c, settings = doc["cycle"], doc["settings"]
    body = [[who, str(r["cycles"]), str(r["late"]), f"{r['late_percent']:.3f}", str(r["lost"]),
             str(r["wkc_errors"])] for who, r in (("ups ethercat", c["ups"]),
                                                   ("bare pysoem loop", c["pysoem"]))]  # fmt: skip
    out = [(f"EtherCAT cycle, {settings['cycle_ms']:g} ms for {settings['seconds']:g} s (late: "
            f"started over half a period after its time; ups / pysoem late: "
            f"{c['late_ratio']:.2f}x)",
            ["master", "cycles", "late", "late %", "lost", "wkc errors"], body)]  # fmt: skip
    body = []
    for key, row in doc["paths"].items():
        s = row["one_way_ms"] or {}
        body.append(
            [
                PATHS[key],
                str(row["n"]),
                str(row["lost"]),
                *(f"{s[k]:.3f}" if k in s else "-" for k in ("p50", "mean", "p99", "max")),
            ]
        )
    out.append((f"EtherCAT paths, one way in ms ({settings['messages']} samples "
                f"{settings['gap_ms']:g} ms apart)",
                ["path", "n", "lost", "p50", "mean", "p99", "max"], body))  # fmt: skip
    return out


def text(doc: dict[str, Any]) -> str:
    parts = []
    for title, head, body in tables(doc):
        widths = [max(len(r[i]) for r in [head, *body]) for i in range(len(head))]
        rows = [head, *body]
        parts.append(title + "\n" + "\n".join(
            "  ".join(cell.ljust(w) if i == 0 else cell.rjust(w)
                      for i, (cell, w) in enumerate(zip(row, widths, strict=True)))
            for row in rows))  # fmt: skip
    return "\n\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cycle", type=float, default=2.0, help="ms between exchanges (2)")
    p.add_argument("--seconds", type=float, default=60.0, help="seconds of each cycle run (60)")
    p.add_argument("--messages", type=int, default=300, help="samples a path (300)")
    p.add_argument("--gap", type=float, default=10.0, help="ms between samples (10)")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    check_private_namespace()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))  # the children are stopped on the way
    with tempfile.TemporaryDirectory(prefix="ups-ecat-bench-") as tmp, veth() as (master, wire):
        doc: dict[str, Any] = {"cycle": cycle_part(master, wire, Path(tmp), args)}
        (Path(tmp) / "me").unlink()
        doc["paths"] = asyncio.run(paths_part(master, wire, Path(tmp), args))
    doc["settings"] = {"cycle_ms": args.cycle, "seconds": args.seconds,
                       "messages": args.messages, "gap_ms": args.gap}  # fmt: skip
    print(text(doc))
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--bare":
        print(json.dumps(bare_loop(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))))
    else:
        sys.exit(main())
