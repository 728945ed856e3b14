"""What ``benchmarks.table5`` prints: the paper's Table 5 beside today's round trips (``Rtt``
rows, pinned and unpinned), where the time of each goes, and the gateway's forwarding rates
beside a saturated CAN bus."""

from __future__ import annotations

import argparse
import statistics
from dataclasses import dataclass, field
from typing import Any

# Table 5 of the paper, min / avg / max in microseconds (Pentium III 800 MHz, C167 20 MHz).
PAPER = {
    "tcp_local": ("PC1 -> PC1", (361, 421, 493)),
    "tcp_veth": ("PC1 -> PC2 (Ethernet)", (981, 1020, 1083)),
    "tcp_gw_can": ("PC1 -> gw -> C167", (4060, 4099, 4323)),
    "can_gw_tcp": ("C167 -> gw -> PC1", (4204, 4350, 6068)),
    "can_can": ("C167 -> RTLinux", (3757, 3769, 3772)),
}
PAPER_RTLINUX_VIA_GW = (1103, 1248, 2910)  # PC1 -> gateway -> PC3 (RTLinux CAN node)

# Classic CAN at 1 Mbit/s, extended identifiers: frames per second on a saturated bus.
BUS_FPS = {"8-byte, worst-case stuffing": 1e6 / 160, "8-byte, no stuffing": 1e6 / 131}
BUS_FPS_1BYTE = (11_000, 13_000)


@dataclass
class Rtt:
    """One path in one pinning mode."""

    key: str
    label: str
    pinned: bool
    rtt_us: list[float] = field(default_factory=list)
    legs: dict[str, list[float]] = field(default_factory=dict)
    probes: int = 0
    setup_s: float = 0.0
    lost: int = 0
    error: str = ""

    def summary(self) -> tuple[float, float, float, float, float] | None:
        if not self.rtt_us:
            return None
        us = sorted(self.rtt_us)
        p99 = us[min(len(us) - 1, int(len(us) * 0.99))]
        return us[0], statistics.median(us), statistics.fmean(us), p99, us[-1]


def p50(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def print_round_trips(rows: list[Rtt], args: argparse.Namespace) -> None:
    modes = sorted({r.pinned for r in rows})
    print()
    print(
        f"Table 5 today: round trips of 8-byte events, {args.roundtrips} after {args.warmup} "
        f"warm-ups, µs (min / p50 / avg / p99 / max)"
    )
    header = f"{'path':44}"
    for pinned in modes:
        header += f" | {'pinned to CPU 0' if pinned else 'unpinned':^36}"
    header += " | paper min / avg / max"
    print(header)
    seen: list[str] = []
    for r in rows:
        if r.key not in seen:
            seen.append(r.key)
    for key in seen:
        mine = {r.pinned: r for r in rows if r.key == key}
        label = next(iter(mine.values())).label
        line = f"{label:44}"
        for pinned in modes:
            cell = mine.get(pinned)
            s = cell.summary() if cell else None
            if s is None:
                line += f" | {'(failed)' if cell and cell.error else '':^36}"
            else:
                line += " | " + f"{' '.join(f'{v:6.0f}' for v in s):36}"
        if key in PAPER:
            name, (lo, avg, hi) = PAPER[key]
            line += f" | {lo} / {avg} / {hi}  {name}"
        print(line)
        if key == "tcp_gw_can":
            lo, avg, hi = PAPER_RTLINUX_VIA_GW
            pad = "".join(f" | {'':36}" for _ in modes)
            print(f"{'':44}{pad} | {lo} / {avg} / {hi}  PC1 -> gw -> RTLinux")
    print()
    print("Where the time goes (p50, µs): 'out' = ping publish -> echo holds it, 'back' = echo")
    print("publishes -> pinger holds it; 'rx->app' = from the receiver's message timestamp (CAN:")
    print("the kernel's receive time of the datagram; TCP: when the TCP face decoded it) until")
    print("the waiting task has it. Shared wall clock, so one-way legs are real.")
    print(
        f"{'path':44} {'mode':9} {'out':>7} {'rx->app':>8} {'back':>7} {'rx->app':>8} "
        f"{'probes':>6} {'setup s':>7} {'lost':>4}"
    )
    for r in rows:
        if not r.legs:
            continue
        print(
            f"{r.label:44} {'pinned' if r.pinned else 'unpinned':9} {p50(r.legs['out']):7.0f} "
            f"{p50(r.legs['out_rx']):8.0f} {p50(r.legs['back']):7.0f} "
            f"{p50(r.legs['back_rx']):8.0f} {r.probes:6d} {r.setup_s:7.2f} {r.lost:4d}"
        )
    for pinned in modes:
        p50s = {r.key: p50(r.rtt_us) for r in rows if r.pinned == pinned and r.rtt_us}
        if all(k in p50s for k in ("tcp_local", "can_can", "tcp_gw_can", "can_gw_tcp")):
            base = p50s["tcp_local"] + p50s["can_can"]
            print(
                f"({'pinned' if pinned else 'unpinned'}, p50: path 3 {p50s['tcp_gw_can']:.0f} µs, "
                f"path 4 {p50s['can_gw_tcp']:.0f} µs vs path 1 + path 5 = {base:.0f} µs: a TCP "
                "and a CAN round trip, as if the gateway were just one more node)"
            )


def print_rates(steps: list[dict[str, Any]], args: argparse.Namespace) -> None:
    print()
    print(
        f"CAN -> gateway -> TCP forwarding, {args.events} events of 8 bytes per step, "
        f"{args.flat_events} flat out (udp_multicast publisher, TCP subscriber)"
    )
    print("pacing 'timer': the publisher sends what is due each 1 ms timer tick (bursts); 'spin':")
    print("it busy-waits to space events evenly, as a real bus would (one whole CPU for it).")
    print(
        f"{'pacing':6} {'asked':>9} {'sent/s':>8} {'recv/s':>8} {'received':>9} {'lost':>6} "
        f"{'loss':>6} {'ooo':>4} {'gw CPU%':>7} {'gw µs/ev':>8} {'udp drop':>8} {'tcp drop':>8} "
        f"{'tx fail':>7}"
    )
    best: dict[str, dict[str, Any]] = {}
    for s in steps:
        asked = "flat out" if s["rate"] <= 0 else f"{s['rate']:.0f}"
        per_event = 1e6 * s["gw_cpu_s"] / max(1, s["received"])
        loss = 100 * s["lost"] / max(1, s["sent"])
        print(
            f"{s['pacing']:6} {asked:>9} {s['send_rate']:8.0f} {s['recv_rate']:8.0f} "
            f"{s['unique']:9d} {s['lost']:6d} {loss:5.1f}% {s['out_of_order']:4d} "
            f"{s['gw_cpu_pct']:7.0f} {per_event:8.1f} {s['gw_udp_drops']:8d} "
            f"{s['gw_tcp_dropped']:8d} {s['tx_failed']:7d}"
        )
        top = best.get(s["pacing"])
        if s["lost"] == 0 and (top is None or s["recv_rate"] > top["recv_rate"]):
            best[s["pacing"]] = s
    lo, hi = BUS_FPS["8-byte, worst-case stuffing"], BUS_FPS["8-byte, no stuffing"]
    print(
        f"A saturated 1 Mbit/s classic CAN bus carries {lo:.0f}-{hi:.0f} 8-byte frames/s "
        f"({BUS_FPS_1BYTE[0]}-{BUS_FPS_1BYTE[1]} 1-byte frames/s)."
    )
    for pacing in dict.fromkeys(s["pacing"] for s in steps):
        top = best.get(pacing)
        if top is None:
            print(f"{pacing}: no step was free of loss.")
            continue
        per_event = 1e6 * top["gw_cpu_s"] / max(1, top["received"])
        print(
            f"{pacing}: highest rate with zero loss {top['recv_rate']:.0f} events/s "
            f"({top['recv_rate'] / hi:.1f}x a saturated bus of 8-byte frames, "
            f"{top['recv_rate'] / BUS_FPS_1BYTE[1]:.1f}x of 1-byte ones); gateway CPU "
            f"{top['gw_cpu_pct']:.0f}% of one core there, {per_event:.1f} µs per event."
        )
