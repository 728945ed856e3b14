"""Round trips across TCP/IP, the gateway and CAN, as in Table 5 of the paper; and the gateway's
CAN->TCP forwarding rate beside a saturated CAN bus.

Round trips, 8-byte payloads: a *pinger* process publishes on a ping channel and waits for an
*echo* process to publish the same bytes back on a pong channel; one at a time, N of them
after W warm-ups, each timed with ``perf_counter_ns`` in the pinger. Before measuring, the pinger
probes (bounded) until a round trip succeeds, as subscriptions reach the gateway asynchronously.
The paths, side by side in one run:

1. TCP host -> TCP host, same host (loopback).
2. TCP host -> TCP host, two network namespaces joined by a veth pair (the broker in one).
3. TCP host -> gateway -> CAN node -> back.
4. CAN node -> gateway -> TCP host -> back.
5. CAN node -> CAN node -> back, no gateway on the path (the paper's C167 <-> RTLinux rows).
6. Floors without middleware: a blocking python-can udp_multicast echo, a blocking TCP echo.

Every path runs unpinned and with the pinger, the echo and (on gateway paths) the gateway
pinned to CPU 0. All processes share one clock, so the payload (the pinger's ``time_ns``) also
splits each round trip into its two one-way legs; for a CAN receiver the leg is split again
at the kernel's receive timestamp of the UDP datagram (SO_TIMESTAMPNS).

Rate: a CAN publisher process sends K 8-byte events at each given rate (and F flat out, long
enough to overrun the gateway's socket buffer if the gateway is slower than the publisher),
either in 1 ms timer ticks (bursts) or busy-waiting to space them evenly as a real bus does. A
TCP subscriber process counts what the gateway forwards (sequence numbers: loss, order); the
gateway's CPU time (``/proc/PID/stat``), its UDP socket drops (``/proc/net/udp``) and its
counters (``ups status``) are read around each step. Compare with a saturated 1 Mbit/s bus:
6.3-7.6k 8-byte frames/s.

CAN is python-can's udp_multicast, which must stay inside a private network namespace:

    scripts/netns-run .venv/bin/python -m ups.benchmarks.table5 [--roundtrips N] [--warmup W]
        [--events K] [--flat-events F] [--rates 2000,...,50000,0] [--pacing timer,spin]
        [--pin both|off|on] [--no-veth] [--no-rate] [--json PATH]

Each daemon and measuring process is a child started here; every wait has a timeout, and every
child is stopped by its PID (SIGTERM, then SIGKILL). The two namespaces of path 2 are deleted
on the way out, also after an error.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ups.benchmarks._procs import SETUP_TIMEOUT, Child, set_affinity
from ups.benchmarks._table5_report import Rtt, print_rates, print_round_trips
from ups.benchmarks._table5_roles import run_child

GW_ID = 0x6A7E


# =============================================================================================
# The harness: daemons, children, namespaces
# =============================================================================================


def role_argv(role: str, cfg: dict[str, Any], netns: str | None = None) -> list[str]:
    argv = [sys.executable, "-m", "ups.benchmarks.table5", "--child", role, json.dumps(cfg)]
    return ["ip", "netns", "exec", netns, *argv] if netns else argv


def ups_argv(*args: str, netns: str | None = None) -> list[str]:
    argv = [sys.executable, "-m", "upscli", *args]
    return ["ip", "netns", "exec", netns, *argv] if netns else argv


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of ``pid`` so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def udp_drops(pid: int) -> int:
    """Datagrams dropped at the UDP sockets of ``pid`` (receive buffer full), this namespace."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    drops = 0
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        with contextlib.suppress(OSError):
            for row in Path(table).read_text().splitlines()[1:]:
                cols = row.split()
                if cols[9] in inodes:
                    drops += int(cols[-1])
    return drops


def status(address: str) -> dict[str, Any]:
    from ups._tcpquery import query_status

    return dict(asyncio.run(query_status(address, timeout=10)))


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def check_private_namespace() -> None:
    """udp_multicast must never leave the machine: only inside scripts/netns-run."""
    routes = subprocess.run(
        ["ip", "route", "show", "default"], capture_output=True, text=True, check=False
    )
    if os.environ.get("UPS_IN_NETNS") != "1" or routes.returncode or routes.stdout.strip():
        sys.exit("run inside a private network namespace: scripts/netns-run .venv/bin/python ...")


@contextlib.contextmanager
def veth_pair() -> Iterator[tuple[str, str]]:
    """Two namespaces joined by a veth pair, 10.77.0.1/24 and 10.77.0.2/24; deleted at exit."""
    tag = f"{os.getpid() % 100000}"
    ns_a, ns_b = f"ups-t5-{tag}-a", f"ups-t5-{tag}-b"
    dev_a, dev_b = f"t5a{tag}"[:15], f"t5b{tag}"[:15]
    made: list[str] = []
    try:
        for ns in (ns_a, ns_b):
            subprocess.run(["ip", "netns", "add", ns], check=True)
            made.append(ns)
        commands = [
            ["ip", "link", "add", dev_a, "type", "veth", "peer", "name", dev_b],
            ["ip", "link", "set", dev_a, "netns", ns_a],
            ["ip", "link", "set", dev_b, "netns", ns_b],
            ["ip", "-n", ns_a, "addr", "add", "10.77.0.1/24", "dev", dev_a],
            ["ip", "-n", ns_b, "addr", "add", "10.77.0.2/24", "dev", dev_b],
        ]
        for ns, dev in ((ns_a, dev_a), (ns_b, dev_b)):
            commands += [["ip", "-n", ns, "link", "set", "lo", "up"]]
            commands += [["ip", "-n", ns, "link", "set", dev, "up"]]
        for cmd in commands:
            subprocess.run(cmd, check=True)
        yield ns_a, ns_b
    finally:
        for ns in made:  # deleting a namespace deletes its end of the pair, and so both ends
            subprocess.run(["ip", "netns", "del", ns], check=False)


# =============================================================================================
# Measurements
# =============================================================================================


@dataclass
class Route:
    key: str
    label: str
    ping_net: str
    echo_net: str
    gateway: bool = False
    ping_ns: str | None = None
    echo_ns: str | None = None
    raw: str = ""  # "can" or "tcp": a floor without UPS


class Bench:
    def __init__(self, args: argparse.Namespace, tmp: Path) -> None:
        self.args = args
        self.tmp = tmp
        self.bus = args.can or f"udp_multicast:239.74.163.2,port={free_udp_port()}"
        self.children: list[Child] = []
        self.daemons: list[Child] = []
        self.gateway: Child | None = None
        self.gateway_status = ""
        self.broker = ""
        self.next_id = 0x7AB1E5_000
        self.all_cpus = os.sched_getaffinity(0)

    def node_id(self) -> int:
        self.next_id += 1
        return self.next_id

    def spawn(self, argv: list[str], label: str) -> Child:
        child = Child(argv, label)
        self.children.append(child)
        return child

    def close(self) -> None:
        for child in reversed(self.children):
            child.stop()

    # --- daemons ---------------------------------------------------------------------------

    def start_broker(self, host: str = "127.0.0.1", netns: str | None = None) -> str:
        proc = self.spawn(
            ups_argv("broker", "--listen", f"{host}:0", "--recovery", "0", netns=netns),
            f"broker {host}",
        )
        self.daemons.append(proc)
        return proc.wait_stderr(r"TCP-ECB on (\S+:\d+)").group(1)

    def start_gateway(self) -> None:
        self.gateway = self.spawn(
            ups_argv(
                "gateway", "--can", self.bus, "--broker", self.broker,
                "--db", str(self.tmp / "gw.db"), "--node-id", hex(GW_ID),
                "--bitrate", "1000000", "--listen", "127.0.0.1:0",
            ),
            "gateway",
        )  # fmt: skip
        self.daemons.append(self.gateway)
        self.gateway_status = self.gateway.wait_stderr(r"listening on (\S+:\d+)").group(1)

    # --- round trips -----------------------------------------------------------------------

    def round_trip(self, path: Route, pinned: bool, tag: str) -> Rtt:
        row = Rtt(path.key, path.label, pinned)
        cpu = 0 if pinned else None
        if self.gateway is not None:
            set_affinity(self.gateway.pid, {0} if pinned and path.gateway else self.all_cpus)
        common = {
            "cpu": cpu,
            "lifetime": 600.0,
            "count": self.args.roundtrips,
            "warmup": self.args.warmup,
            "gap": self.args.gap / 1000,
            "probe_timeout": 0.25,
            "setup_timeout": SETUP_TIMEOUT,
        }
        echo: Child | None = None
        ping: Child | None = None
        try:
            if path.raw == "tcp":
                echo = self.spawn(role_argv("raw_tcp_echo", common), f"{tag} echo")
                port = echo.event(SETUP_TIMEOUT)["port"]
                ping = self.spawn(role_argv("raw_tcp_ping", {**common, "port": port}), tag)
            elif path.raw == "can":
                cfg = {**common, "bus": self.bus}
                echo = self.spawn(role_argv("raw_can_echo", cfg), f"{tag} echo")
                echo.event(SETUP_TIMEOUT)
                ping = self.spawn(role_argv("raw_can_ping", cfg), tag)
            else:
                channels = {"ping": f"table5/{tag}/ping", "pong": f"table5/{tag}/pong"}
                echo_cfg = {**common, **channels, "net": path.echo_net, "node_id": self.node_id()}
                echo = self.spawn(role_argv("echo", echo_cfg, path.echo_ns), f"{tag} echo")
                echo.event(SETUP_TIMEOUT)
                ping_cfg = {**common, **channels, "net": path.ping_net, "node_id": self.node_id()}
                ping = self.spawn(role_argv("ping", ping_cfg, path.ping_ns), tag)
            budget = 2 * SETUP_TIMEOUT + (self.args.roundtrips + self.args.warmup) * 0.1
            result = ping.event(budget)
            row.rtt_us = [s[3] / 1000 for s in result["samples"]]
            row.probes, row.lost = result["probes"], result["lost"]
            row.setup_s = result.get("setup_s", 0.0)
            ping.finish()
            if not path.raw:
                echo.send("stop")
                records = echo.event(SETUP_TIMEOUT)["records"]
                row.legs = legs(result["samples"], records, path)
            echo.finish()
        except RuntimeError as exc:
            row.error = str(exc).splitlines()[0][:200]
            print(f"  {tag}: {exc}", file=sys.stderr)
        finally:
            for child in (ping, echo):
                if child is not None:
                    child.stop()
        return row

    # --- CAN -> TCP rate -------------------------------------------------------------------

    def rate(self) -> list[dict[str, Any]]:
        assert self.gateway is not None
        set_affinity(self.gateway.pid, self.all_cpus)
        gw = self.gateway.pid
        channel = "table5/rate"
        sub = self.spawn(
            role_argv(
                "rate_sub", {"net": f"tcp:{self.broker}", "channel": channel, "node_id": 0x5B}
            ),
            "rate subscriber",
        )
        sub.event(SETUP_TIMEOUT)
        pub = self.spawn(
            role_argv("rate_pub", {"net": f"can:{self.bus}", "channel": channel, "node_id": 0x5C}),
            "rate publisher",
        )
        pub.event(SETUP_TIMEOUT)
        sub.event(SETUP_TIMEOUT)  # "path": a probe went CAN -> gateway -> TCP
        steps = []
        plan = [(p, r) for p in self.args.pacing for r in self.args.rates if r > 0 or p == "timer"]
        for index, (pacing, rate) in enumerate(plan):
            time.sleep(0.5)  # let the previous step drain
            k = self.args.events if rate > 0 else self.args.flat_events
            before = (cpu_seconds(gw), udp_drops(gw), status(self.gateway_status)["gateway"])
            pub.send(f"run {index} {rate} {k} {pacing}")
            done = pub.event(SETUP_TIMEOUT + k / max(rate, 1000.0) * 3)
            sub.send(f"report {index} {k}")
            report = sub.event(30.0)
            after = (cpu_seconds(gw), udp_drops(gw), status(self.gateway_status)["gateway"])
            span = max(report["span_s"], 1e-9)
            step = {
                "pacing": pacing,
                "rate": rate,
                "sent": done["sent"],
                "send_rate": done["sent"] / done["duration_s"],
                "tx_failed": done["tx_failed"],
                "received": report["received"],
                "unique": report["unique"],
                "lost": done["sent"] - report["unique"],
                "out_of_order": report["out_of_order"],
                "recv_rate": (report["received"] - 1) / span if report["received"] > 1 else 0.0,
                "gw_cpu_s": after[0] - before[0],
                "gw_cpu_pct": 100 * (after[0] - before[0]) / max(span, done["duration_s"]),
                "gw_udp_drops": after[1] - before[1],
                "gw_to_tcp": after[2]["to_tcp"] - before[2]["to_tcp"],
                "gw_tcp_dropped": after[2]["tcp_dropped"] - before[2]["tcp_dropped"],
                "sub_dropped": report["stats"].get("dropped", 0),
            }
            steps.append(step)
            label = "flat out" if rate <= 0 else f"{rate:g}/s {pacing}"
            print(
                f"  rate {label}: received {step['unique']}/{k} at {step['recv_rate']:.0f}/s, "
                f"gateway CPU {step['gw_cpu_pct']:.0f}%",
                file=sys.stderr,
            )
        pub.send("quit")
        sub.send("quit")
        pub.finish()
        sub.finish()
        return steps


def legs(samples: list[list[int]], records: list[list[int]], path: Route) -> dict[str, list[float]]:
    """One-way legs of each round trip, from the shared wall clock (µs)."""
    by_sent = {r[0]: r for r in records}
    out: dict[str, list[float]] = {"out": [], "out_rx": [], "back": [], "back_rx": []}
    for sent, back, back_stamp, _ in samples:
        rec = by_sent.get(sent)
        if rec is None:
            continue
        _, recv, stamp, reply = rec
        out["out"].append((recv - sent) / 1000)
        out["out_rx"].append((recv - stamp) / 1000)
        out["back"].append((back - reply) / 1000)
        out["back_rx"].append((back - back_stamp) / 1000)
    return out


# =============================================================================================
# main
# =============================================================================================


def parse_rates(text: str) -> list[float]:
    return [float(t) for t in text.split(",") if t.strip()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--roundtrips", type=int, default=300, help="measured round trips")
    parser.add_argument("--warmup", type=int, default=30, help="round trips before measuring")
    parser.add_argument("--gap", type=float, default=0.0, help="ms between round trips")
    parser.add_argument(
        "--events", type=int, default=20_000, help="events per paced step of the rate test"
    )
    parser.add_argument(
        "--flat-events", type=int, default=200_000, help="events of the flat-out step"
    )
    parser.add_argument(
        "--rates",
        type=parse_rates,
        default=parse_rates("2000,4000,6300,7600,10000,13000,20000,30000,50000,0"),
        help="events/s of each rate step, comma-separated (0: as fast as the publisher can)",
    )
    parser.add_argument(
        "--pacing",
        type=lambda t: [x for x in t.split(",") if x in ("timer", "spin")],
        default=["timer", "spin"],
        help="publisher pacing of the rate test: timer, spin or timer,spin (default)",
    )
    parser.add_argument("--pin", choices=("both", "off", "on"), default="both")
    parser.add_argument("--can", default=None, help="udp_multicast bus (default: a free port)")
    parser.add_argument("--no-veth", action="store_true", help="skip the two-namespace path")
    parser.add_argument("--no-rate", action="store_true", help="skip the rate test")
    parser.add_argument("--json", type=Path, default=None, help="write the raw results here")
    args = parser.parse_args()
    check_private_namespace()
    modes = {"both": [False, True], "off": [False], "on": [True]}[args.pin]

    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        bench = Bench(args, Path(tmp))
        stack.callback(bench.close)
        bench.broker = bench.start_broker()
        bench.start_gateway()
        tcp, can = f"tcp:{bench.broker}", f"can:{bench.bus}"
        paths = [
            Route("tcp_local", "1 TCP host -> TCP host, same host", tcp, tcp),
            Route("tcp_veth", "2 TCP host -> TCP host, two netns over veth", "", ""),
            Route("tcp_gw_can", "3 TCP host -> gateway -> CAN node -> back", tcp, can, True),
            Route("can_gw_tcp", "4 CAN node -> gateway -> TCP host -> back", can, tcp, True),
            Route("can_can", "5 CAN node -> CAN node -> back (no gw)", can, can),
            Route("raw_can", "6a floor: python-can udp_multicast echo", "", "", raw="can"),
            Route("raw_tcp", "6b floor: blocking TCP socket echo", "", "", raw="tcp"),
        ]
        if not args.no_veth:
            ns_a, ns_b = stack.enter_context(veth_pair())
            far = bench.start_broker("10.77.0.1", netns=ns_a)
            paths[1] = Route(
                "tcp_veth", paths[1].label, f"tcp:{far}", f"tcp:{far}", False, ns_a, ns_b
            )
        else:
            del paths[1]
        rows: list[Rtt] = []
        for path in paths:
            for pinned in modes:
                tag = f"{path.key}-{'pin' if pinned else 'free'}"
                print(f"  round trip {tag} ...", file=sys.stderr)
                rows.append(bench.round_trip(path, pinned, tag))
        steps = [] if args.no_rate else bench.rate()
        gw_final = status(bench.gateway_status)["gateway"]

    print(f"\nUPS Table 5 on {bench.bus}, gateway at 1 Mbit/s, {os.cpu_count()} CPUs, "
          f"Python {sys.version.split()[0]}")  # fmt: skip
    print_round_trips(rows, args)
    if steps:
        print_rates(steps, args)
    print(
        f"\ngateway counters at the end: to_tcp={gw_final['to_tcp']} to_can={gw_final['to_can']} "
        f"can_dropped={gw_final['can_dropped']} tcp_dropped={gw_final['tcp_dropped']}"
    )
    for daemon in bench.daemons:
        warnings = [line for line in daemon.stderr if " WARNING" in line or " ERROR" in line]
        print(f"{daemon.label}: {len(warnings)} warnings/errors in its log")
        for line in warnings[:5]:
            print(f"   {line.rstrip()}")
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "bus": bench.bus,
                    "round_trips": [r.__dict__ for r in rows],
                    "rate": steps,
                    "gateway": gw_final,
                },
                indent=1,
            )
        )


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        run_child(sys.argv[2], json.loads(sys.argv[3]))
    else:
        main()
