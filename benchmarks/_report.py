"""What ``ups bench`` prints and writes: tables beside the paper's figures, the issue's targets
met or missed with their ratios, and plots (matplotlib, when installed)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Any

#: the paper's section 6 (PERFORMANCE.md): Pentium III 800 MHz, RTLinux, C167 CAN nodes
PAPER: dict[str, Any] = {
    "local_notify_us": {"1": 17.5, "2": 22.6, "3": 27.9, "4": 34.3},  # Table 3, RTLinux avg
    "publish_latency_us": 153.0,  # Table 4, RTLinux avg
    "rtt_us": {
        "tcp_same_host": 421.0,
        "tcp_two_hosts": 1020.0,
        "tcp_gateway_can": 4099.0,
        "can_gateway_tcp": 4099.0,
    },
    # Table 6: ECH/TCP 53 + ECH/CAN 45 KB, ECB 47 KB, gateway 177 KB (compiled)
    "code_kb": {"ECB (broker)": 47, "ECH (ups, without tools and rt)": 98, "gateway": 177},
}
_PEER_PACKAGES = {
    "zmq": "pyzmq",
    "paho": "paho-mqtt",
    "zenoh": "eclipse-zenoh",
    "uvloop": "uvloop",
    "matplotlib": "matplotlib",
}


def missing_peers() -> list[str]:
    return [dist for mod, dist in _PEER_PACKAGES.items() if importlib.util.find_spec(mod) is None]


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def targets(r: dict[str, Any]) -> list[tuple[str, float | None, str, bool | None]]:
    """(target, measured ratio, what it is measured against, met) for each of issue 11's."""
    rows = r.get("tcp_compare", {}).get("rows", {})
    ups = rows.get("UPS TCP, uvloop") or rows.get("UPS TCP, stdlib loop") or {}
    raw = rows.get("raw TCP", {})
    out: list[tuple[str, float | None, str, bool | None]] = []
    rtt = _ratio(ups.get("rtt_p50_us"), raw.get("rtt_p50_us"))
    out.append(("round trip p50 <= 2x raw TCP", rtt, "raw TCP", None if rtt is None else rtt <= 2))
    others = [
        row.get("rtt_p50_us")
        for label, row in rows.items()
        if not label.startswith(("UPS", "raw", "asyncio")) and row.get("rtt_p50_us")
    ]
    if others and ups.get("rtt_p50_us"):
        best = min(others)
        out.append(
            (
                "round trip below every peer",
                ups["rtt_p50_us"] / best,
                "the fastest peer",
                ups["rtt_p50_us"] < best,
            )
        )
    zmq, zenoh = rows.get("pyzmq PUB/SUB, HWM=0", {}), rows.get("zenoh peer-to-peer", {})
    tput = _ratio(ups.get("rate_msg_s"), zmq.get("rate_msg_s"))
    lossless = not ups.get("lost")
    out.append(
        (
            "throughput >= 0.6x pyzmq, zero loss",
            tput,
            "pyzmq",
            None if tput is None else tput >= 0.6 and lossless,
        )
    )
    vs_zenoh = _ratio(ups.get("rate_msg_s"), zenoh.get("rate_msg_s"))
    out.append(
        ("throughput above zenoh", vs_zenoh, "zenoh", None if vs_zenoh is None else vs_zenoh > 1)
    )
    fan = [row for row in r.get("fanout", []) if row["subscribers"] == 16]
    fan_ratio = fan[0].get("ratio") if fan else None
    out.append(
        (
            "lossless fan-out >= 0.5x pyzmq at 16",
            fan_ratio,
            "pyzmq, HWM=0",
            None if fan_ratio is None else fan_ratio >= 0.5 and not fan[0]["ups"]["lost"],
        )
    )
    mib = [row for row in r.get("payload", []) if row["size"] == 1 << 20]
    mib_ratio = mib[0]["ratio"] if mib else None
    out.append(
        (
            "1 MiB events >= 0.6x raw TCP",
            mib_ratio,
            "raw TCP",
            None if mib_ratio is None else mib_ratio >= 0.6,
        )
    )
    start = r.get("startup", {}).get("ratio")
    out.append(
        (
            "ups --help <= 3x python -c pass",
            start,
            "python -c pass",
            None if start is None else start <= 3,
        )
    )
    idle = r.get("rss_mb", {}).get("idle_tcp_node")
    out.append(("idle TCP node <= 20 MB RSS", idle, "MB", None if idle is None else idle <= 20))
    return out


def text(r: dict[str, Any]) -> str:
    """The tables, as the terminal shows them."""
    m = r["machine"]
    lines = [
        f"ups bench ({'quick' if m['quick'] else 'full'}): {m['cpu']}, {m['cpus']} CPUs, "
        f"Linux {m['kernel']}, Python {m['python']}, {m['date']}",
        "",
    ]
    lines += _section(
        "Paper, section 6 (ours: median µs; paper: average on 2003 hardware)", _paper_rows(r)
    )
    rows = r.get("tcp_compare", {}).get("rows", {})
    if rows:
        raw = rows.get("raw TCP", {})
        lines += _section(
            "Round trip and one-way throughput, 8 B, loopback (same run)",
            [
                (
                    label,
                    f"{_f(row.get('rtt_p50_us'))} µs",
                    f"{_f(_ratio(row.get('rtt_p50_us'), raw.get('rtt_p50_us')), '.2f')}x raw",
                    f"{_f(row.get('rate_msg_s'), ',.0f')} msg/s",
                    f"lost {row.get('lost')}",
                )
                for label, row in rows.items()
                if not row.get("error")
            ],
        )
    if r.get("payload"):
        lines += _section(
            "Payload size, one way, UPS vs raw TCP (same run)",
            [
                (
                    f"{row['size']} B",
                    f"{row['ups']['mb_per_s']:,.0f} MB/s",
                    f"raw {row['raw_tcp']['mb_per_s']:,.0f} MB/s",
                    f"{row['ratio']:.2f}x",
                    f"lost {row['count'] - row['ups']['received']}",
                )
                for row in r["payload"]
            ],
        )
    if r.get("fanout"):
        lines += _section(
            "Lossless fan-out, 8 B, one publisher (deliveries/s in all)",
            [
                (
                    f"{row['subscribers']} subscribers",
                    f"UPS {row['ups']['total_msgs_per_s']:,.0f}",
                    f"pyzmq {_f((row['zmq'] or {}).get('total_msgs_per_s'), ',.0f')}",
                    f"{_f(row.get('ratio'), '.2f')}x",
                    f"lost {row['ups']['lost']}",
                )
                for row in r["fanout"]
            ],
        )
    gw = r.get("throughput_msgs_per_s", {}).get("gateway_can_to_tcp")
    if gw:
        lines += [
            f"gateway CAN->TCP, zero loss: {gw:,.0f} events/s = "
            f"{gw / 7634:.1f}x a saturated 1 Mbit/s bus of 8-byte frames",
            "",
        ]
    if r.get("rss_mb"):
        lines += _section("Resident memory (MB)", [(k, f"{v:.1f}") for k, v in r["rss_mb"].items()])
    if r.get("startup"):
        s = r["startup"]
        lines += [
            f"start-up: ups --help {s['ups_help_s'] * 1000:.0f} ms, python -c pass "
            f"{s['python_c_pass_s'] * 1000:.0f} ms ({s['ratio']:.1f}x)",
            "",
        ]
    lines += _section(
        "Targets (issue 11)",
        [
            (name, f"{_f(value, '.2f')} ({against})", _met(met))
            for name, value, against, met in targets(r)
        ],
    )
    for key, why in {**r.get("skipped", {}), **r.get("failed", {})}.items():
        lines.append(f"{key}: {why.splitlines()[0] if why else ''}")
    return "\n".join(lines)


def _paper_rows(r: dict[str, Any]) -> list[tuple[str, ...]]:
    rows: list[tuple[str, ...]] = []
    for n, ours in (r.get("local_notify_us") or {}).items():
        rows.append(
            (
                f"local notification, {n} subscriber(s)",
                f"{ours:.0f}",
                f"paper {PAPER['local_notify_us'][n]}",
            )
        )
    if r.get("publish_latency_us"):
        rows.append(
            (
                "publish -> frame on the bus",
                f"{r['publish_latency_us']:.0f}",
                f"paper {PAPER['publish_latency_us']:.0f}",
            )
        )
    for key, value in r.get("rtt_us", {}).items():
        rows.append(
            (
                f"round trip {key}",
                f"p50 {value['p50']:.0f} p99 {value['p99']:.0f}",
                f"paper {PAPER['rtt_us'][key]:.0f}",
            )
        )
    for label, size in r.get("code_size", {}).items():
        paper = PAPER["code_kb"].get(label)
        rows.append(
            (
                f"code: {label}",
                f"{size['kb']} KB of source, {size['lines']} lines",
                f"paper {paper} KB compiled" if paper else "",
            )
        )
    return rows


def _section(title: str, rows: list[tuple[str, ...]]) -> list[str]:
    if not rows:
        return []
    widths = [max(len(row[i]) for row in rows if i < len(row)) for i in range(len(rows[0]))]
    body = [
        "  " + "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=False))
        for row in rows
    ]
    return [title, *body, ""]


def _f(value: float | None, spec: str = ".0f") -> str:
    return "-" if value is None else format(value, spec)


def _met(met: bool | None) -> str:
    return "not measured" if met is None else "met" if met else "MISSED"


def write(r: dict[str, Any], where: Path) -> None:
    """report.md, results.json and PNG plots in ``where``."""
    where.mkdir(parents=True, exist_ok=True)
    (where / "results.json").write_text(json.dumps(r, indent=1, default=str))
    plots = _plots(r, where)
    md = ["# ups bench", "", "```", text(r), "```", ""]
    md += [f"![{name}]({name})" for name in plots]
    (where / "report.md").write_text("\n".join(md) + "\n")


def _plots(r: dict[str, Any], where: Path) -> list[str]:
    if importlib.util.find_spec("matplotlib") is None:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []
    rows = {
        k: v for k, v in r.get("tcp_compare", {}).get("rows", {}).items() if v.get("rtt_p50_us")
    }
    if rows:
        fig, ax = plt.subplots(figsize=(8, 4))
        ax.barh(list(rows), [v["rtt_p50_us"] for v in rows.values()])
        ax.set_xlabel("round trip p50 (µs), 8 B, loopback, pinned")
        made.append(_save(fig, where, "rtt.png"))
    if r.get("fanout"):
        fig, ax = plt.subplots(figsize=(6, 4))
        n = [row["subscribers"] for row in r["fanout"]]
        ax.plot(n, [row["ups"]["total_msgs_per_s"] for row in r["fanout"]], "o-", label="UPS")
        if all(row["zmq"] for row in r["fanout"]):
            ax.plot(n, [row["zmq"]["total_msgs_per_s"] for row in r["fanout"]], "s-", label="pyzmq")
        ax.set_xscale("log", base=2)
        ax.set(xlabel="subscribers", ylabel="deliveries/s, lossless")
        ax.legend()
        made.append(_save(fig, where, "fanout.png"))
    if r.get("payload"):
        fig, ax = plt.subplots(figsize=(6, 4))
        sizes = [row["size"] for row in r["payload"]]
        ax.plot(sizes, [row["ups"]["mb_per_s"] for row in r["payload"]], "o-", label="UPS")
        ax.plot(sizes, [row["raw_tcp"]["mb_per_s"] for row in r["payload"]], "s-", label="raw")
        ax.set_xscale("log", base=2)
        ax.set(xlabel="payload (bytes)", ylabel="MB/s one way")
        ax.legend()
        made.append(_save(fig, where, "payload.png"))
    if r.get("local_notify_us"):
        fig, ax = plt.subplots(figsize=(6, 4))
        n = list(r["local_notify_us"])
        ax.plot(n, list(r["local_notify_us"].values()), "o-", label="UPS today (p50)")
        ax.plot(n, [PAPER["local_notify_us"][k] for k in n], "s--", label="paper (RTLinux avg)")
        ax.set(xlabel="local subscribers", ylabel="µs")
        ax.legend()
        made.append(_save(fig, where, "local_notify.png"))
    return made


def _save(fig: Any, where: Path, name: str) -> str:
    fig.tight_layout()
    fig.savefig(where / name, dpi=100)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return name
