"""What ``ups bench`` prints and writes: tables beside the paper's figures and the floors and
peers of the same run, the project's targets met or missed with their ratios, and plots
(matplotlib, when installed). The same tables go to the terminal (aligned text) and to
report.md (Markdown)."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path
from typing import Any

from ups.benchmarks._plots import plots
from ups.benchmarks._tables import Table, aligned
from ups.benchmarks.tcp_compare import span

#: the paper's section 6 (PERFORMANCE.md, table5.PAPER): Pentium III 800 MHz, RTLinux, C167
PAPER: dict[str, Any] = {
    "local_notify_us": {"1": 17.5, "2": 22.6, "3": 27.9, "4": 34.3},  # Table 3, RTLinux avg
    "publish_latency_us": 153.0,  # Table 4, RTLinux avg
    "rtt_us": {  # Table 5, averages
        "tcp_same_host": 421.0,  # PC1 -> PC1
        "tcp_two_hosts": 1020.0,  # PC1 -> PC2, Ethernet
        "tcp_gateway_can": 4099.0,  # PC1 -> gw -> C167
        "can_gateway_tcp": 4350.0,  # C167 -> gw -> PC1
        "can_can": 3769.0,  # C167 -> RTLinux
    },
    # Table 6: ECH/TCP 53 + ECH/CAN 45 KB, ECB 47 KB, gateway 177 KB (compiled)
    "code_kb": {"ECB (broker)": 47, "ECH (ups, without tools and rt)": 98, "gateway": 177},
}
RTT_LABELS = {
    "tcp_same_host": "TCP same host",
    "tcp_two_hosts": "TCP two hosts (netns + veth)",
    "tcp_gateway_can": "TCP -> gateway -> CAN node",
    "can_gateway_tcp": "CAN node -> gateway -> TCP",
    "can_can": "CAN node -> CAN node",
}
UPS_ROWS = ("UPS TCP, uvloop", "UPS TCP, stdlib loop")
COMPILED_ROW = "UPS TCP, uvloop, compiled"  # the build UPS_COMPILE=1 makes (see setup.py)
BUS = 7634  # a saturated 1 Mbit/s classic bus, 8-byte extended frames, no stuffing
_PEER_PACKAGES = {
    "zmq": "pyzmq",
    "paho": "paho-mqtt",
    "zenoh": "eclipse-zenoh",
    "uvloop": "uvloop",
    "matplotlib": "matplotlib",
}
#: what each figure of the paper's section is, exactly
NOTES = [
    "local notification (Table 3): from the kernel's receive timestamp of the frame's "
    "datagram (udp_multicast, SO_TIMESTAMPNS) until the last of N subscriber tasks holds the "
    "event; floor: python-can's blocking recv of the same frames, same run.",
    "publish -> frame on the bus (Table 4): from the publish() call until the kernel's receive "
    "timestamp of the frame at a plain python-can listener on the same bus, same process.",
    "round trips (Table 5): 8 B, one at a time, pinger/echo/gateway pinned to one CPU, UPS's "
    "default path (get_msg, awaited publish); floors: blocking TCP and python-can echoes. "
    "The peers' table runs UPS's fast path instead (callback subscriptions, publish_nowait).",
    "one way: the rate at the sink, first to last arrival, every event counted (lost); UPS "
    "publishes with backpressure (wait=True) in the payload and fan-out tables, pyzmq with "
    "HWM=0; raw TCP is a blocking socket with a 4-byte length before each message.",
    "code size (Table 6): Python source here, compiled C (RTLinux modules) in the paper.",
    "Zenoh face (benchmarks/zenoh_face.py): every client through one `ups zenoh-router` "
    "process. Round trip pinned as above; raw zenoh is two plain client sessions with the "
    "face's publisher settings (reliable, congestion DROP). One way, lossless: flat out, then "
    "paced (1 ms ticks) below what the subscriber took until nothing is lost; the figure is "
    "the subscriber's rate in the best lossless step (UPS TCP: flat out with backpressure). "
    "Gateway: a Gateway on a python-can virtual bus, the whole blast of frames on the bus "
    "before it reads any, then drained to a UPS subscriber process (median of the runs); raw "
    "= a thread reading the same bus and putting each frame on the channel's key.",
    "JAUS (benchmarks/jaus_paper000.py): paper 000's Table 2 method -- minimal Set Authority "
    "messages one at a time, one way = half the round trip, min/mean/max/std -- through "
    "`ups jaus` (answering with an ACK), and JAUS -> UPS CAN echo -> JAUS (an every-change "
    "Event), beside UPS CAN -> CAN echo -> back; 10 ms apart (the paper: 100 ms). Its "
    "tests 6 and 4 ran on Windows XP, a Core 2 Quad 2.4 GHz, 2010.",
    "EtherCAT (benchmarks/ethercat.py): `ups ethercat` against the tests' slave emulator on a "
    "veth pair, its cycle beside a bare pysoem loop of the same period; paths one at a time, "
    "10 ms apart, on one clock. Paper 000 proposes the JEBridge without figures for it.",
]


def missing_peers() -> list[str]:
    """The bench extra's packages (and the mosquitto binary) that are not installed."""
    gone = [d for mod, d in _PEER_PACKAGES.items() if importlib.util.find_spec(mod) is None]
    if not (shutil.which("mosquitto") or shutil.which("mosquitto", path="/usr/sbin:/sbin")):
        gone.append("mosquitto")
    return gone


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def _f(value: float | None, spec: str = ".0f", suffix: str = "") -> str:
    return "-" if value is None else format(value, spec) + suffix


def _x(a: float | None, b: float | None) -> str:
    return _f(_ratio(a, b), ".2f", "x")


def _ups_row(r: dict[str, Any]) -> dict[str, Any]:
    rows = r.get("tcp_compare", {}).get("rows", {})
    return next((rows[k] for k in UPS_ROWS if rows.get(k, {}).get("rtt_p50_us")), {})


def targets(r: dict[str, Any]) -> list[tuple[str, float | None, str, bool | None]]:
    """(target, measured, against what, met) for each of the project's targets (set when the
    benchmarks began); met is None when the figure was not measured in this run."""
    rows = r.get("tcp_compare", {}).get("rows", {})
    ups, raw = _ups_row(r), rows.get("raw TCP", {})
    out: list[tuple[str, float | None, str, bool | None]] = []

    def add(name: str, value: float | None, against: str, ok: bool) -> None:
        out.append((name, value, against, None if value is None else ok))

    builds = [("", ups, "ratio", "ups")]
    compiled = rows.get(COMPILED_ROW, {})
    if compiled.get("rtt_p50_us"):  # the compiled build (UPS_COMPILE=1) is judged on its own
        builds.append((", compiled", compiled, "ratio_compiled", "ups_compiled"))
    zmq, zenoh = rows.get("pyzmq PUB/SUB, HWM=0", {}), rows.get("zenoh peer-to-peer", {})
    others = [
        row["rtt_p50_us"]
        for label, row in rows.items()
        if not label.startswith(("UPS", "raw", "asyncio")) and row.get("rtt_p50_us")
    ]
    fan = next((row for row in r.get("fanout") or [] if row["subscribers"] == 16), None)
    for build, it, fan_ratio, fan_key in builds:
        rtt = _ratio(it.get("rtt_p50_us"), raw.get("rtt_p50_us"))
        add(f"round trip p50 <= 2x raw TCP{build}", rtt, "x raw TCP", rtt is not None and rtt <= 2)
        best = _ratio(it.get("rtt_p50_us"), min(others, default=None))
        add(f"round trip p50 below every peer{build}", best, "x fastest peer",
            best is not None and best < 1)  # fmt: skip
        lossless = not it.get("lost")
        tput = _ratio(it.get("rate_msg_s"), zmq.get("rate_msg_s"))
        add(f"throughput >= 0.6x pyzmq, zero loss{build}", tput, "x pyzmq",
            bool(tput and tput >= 0.6 and lossless))  # fmt: skip
        vz = _ratio(it.get("rate_msg_s"), zenoh.get("rate_msg_s"))
        add(f"throughput above zenoh, zero loss{build}", vz, "x zenoh",
            bool(vz and vz > 1 and lossless))  # fmt: skip
        fr = fan.get(fan_ratio) if fan else None
        fan_lost = ((fan or {}).get(fan_key) or {}).get("lost")
        add(f"lossless fan-out >= 0.5x pyzmq at 16{build}", fr, "x pyzmq HWM=0",
            bool(fr and fr >= 0.5 and not fan_lost))  # fmt: skip
    mib = next((row for row in r.get("payload") or [] if row["size"] == 1 << 20), None)
    mr = mib["ratio"] if mib else None
    add("1 MiB events >= 0.6x raw TCP", mr, "x raw TCP", bool(mr and mr >= 0.6))
    start = (r.get("startup_s") or {}).get("ratio")
    add("ups --help <= 3x python -c pass", start, "x python -c pass", bool(start and start <= 3))
    idle = (r.get("rss_mb") or {}).get("idle_tcp_node")
    add("idle TCP node <= 20 MB RSS", idle, "MB", bool(idle and idle <= 20))
    return out


def _met(met: bool | None) -> str:
    return "not measured" if met is None else "met" if met else "MISSED"


# --- the tables ------------------------------------------------------------------------------


def tables(r: dict[str, Any]) -> list[Table]:
    """Every table of the run, in order; a part that did not run has none."""
    out: list[Table] = []
    p = _paper_rows(r)
    if p:
        head = ["measurement", "UPS p50", "p99", "floor (same run)", "x floor", "paper", "x paper"]
        out.append(("The paper's section 6 on this machine (µs; paper: 2003, averages)", head, p))
    rows = r.get("tcp_compare", {}).get("rows", {})
    if rows:
        raw, ups = rows.get("raw TCP", {}), _ups_row(r)
        body = []
        for label, row in rows.items():
            if row.get("error"):
                status = row["error"] if row["error"].startswith("skipped") else "FAILED"
                body.append([label, "-", "-", "-", "-", "-", "-", "-", "-",
                             status.splitlines()[0]])  # fmt: skip
                continue
            body.append([
                label, _f(row.get("rtt_p50_us"), ".1f"), _f(row.get("rtt_p99_us"), ".1f"),
                span(row.get("rtt_p50_pairs_us")),
                _x(row.get("rtt_p50_us"), raw.get("rtt_p50_us")),
                _x(ups.get("rtt_p50_us"), row.get("rtt_p50_us")),
                _f(row.get("rate_msg_s"), ",.0f"),
                _x(ups.get("rate_msg_s"), row.get("rate_msg_s")), str(row.get("lost")), "ok",
            ])  # fmt: skip
        head = ["peer", "RTT p50 µs", "p99", "p50 of each pair", "x raw TCP", "UPS RTT / it",
                "msg/s one way", "UPS msg/s / it", "lost", ""]  # fmt: skip
        out.append(("Round trip (pinned) and one-way throughput, 8 B, loopback", head, body))
    if r.get("payload"):
        body = [
            [f"{row['size']:,} B", f"{row['count']:,}", f"{row['ups']['events_per_s']:,.0f}",
             f"{row['ups']['mb_per_s']:,.0f}", f"{row['raw_tcp']['events_per_s']:,.0f}",
             f"{row['raw_tcp']['mb_per_s']:,.0f}", f"{row['ratio']:.2f}x",
             str(row["count"] - row["ups"]["received"])]
            for row in r["payload"]
        ]  # fmt: skip
        head = ["payload", "events", "UPS ev/s", "UPS MB/s", "raw ev/s", "raw MB/s", "x raw",
                "UPS lost"]  # fmt: skip
        out.append(("One way by payload size, UPS (wait=True) vs raw TCP (length-prefixed)",
                    head, body))  # fmt: skip
    if r.get("fanout"):
        body = []
        for row in r["fanout"]:
            z, c = row.get("zmq") or {}, row.get("ups_compiled") or {}
            body.append([
                str(row["subscribers"]), f"{row['ups']['total_msgs_per_s']:,.0f}",
                f"{row['ups']['per_subscriber_msgs_per_s']:,.0f}",
                _f(c.get("total_msgs_per_s"), ",.0f"),
                _f(z.get("total_msgs_per_s"), ",.0f"), _f(z.get("per_subscriber_msgs_per_s"),
                ",.0f"), _f(row.get("ratio"), ".2f", "x"),
                _f(row.get("ratio_compiled"), ".2f", "x"), str(row["ups"]["lost"]),
                str(c.get("lost", "-")),
                str(z.get("lost", "skipped" if not z else z.get("error", "-"))),
            ])  # fmt: skip
        head = ["subscribers", "UPS total/s", "UPS per sub/s", "compiled total/s",
                "pyzmq total/s", "pyzmq per sub/s", "x pyzmq", "compiled x pyzmq", "UPS lost",
                "compiled lost", "pyzmq lost"]  # fmt: skip
        out.append(("Lossless fan-out, 8 B, one publisher, N subscriber processes", head, body))
    rate = r.get("table5", {}).get("rate") or []
    if rate:
        body = [
            [f"{s['pacing']} {s['rate']:,.0f}/s" if s["rate"] else f"{s['pacing']} flat out",
             f"{s['send_rate']:,.0f}", f"{s['recv_rate']:,.0f}", str(s["lost"]),
             f"{s['gw_cpu_pct']:.0f} %", f"{s['recv_rate'] / BUS:.2f}x"]
            for s in rate
        ]  # fmt: skip
        head = ["offered", "sent/s", "forwarded/s", "lost", "gateway CPU", "x saturated bus"]
        out.append((f"Gateway CAN -> TCP (a saturated 1 Mbit/s bus: {BUS:,} frames/s)",
                    head, body))  # fmt: skip
    if r.get("zenoh_face"):
        from ups.benchmarks.zenoh_face import tables as zenoh_tables

        out += zenoh_tables(r["zenoh_face"])
    if r.get("jaus_paper000"):
        from ups.benchmarks.jaus_paper000 import tables as jaus_tables

        out += jaus_tables(r["jaus_paper000"])
    if r.get("ethercat"):
        from ups.benchmarks.ethercat import tables as ethercat_tables

        out += ethercat_tables(r["ethercat"])
    if r.get("rss_mb"):
        bare = r["rss_mb"].get("python_bare")
        body = [[k, f"{v:.1f}", _x(v, bare)] for k, v in r["rss_mb"].items()]
        out.append(("Resident memory once started (VmRSS)", ["process", "MB", "x python"], body))
    s = r.get("startup_s")
    if s:
        body = [["python -c pass", f"{s['python_c_pass'] * 1000:.0f}", "1.00x"],
                ["ups --help", f"{s['ups_help'] * 1000:.0f}", f"{s['ratio']:.2f}x"]]  # fmt: skip
        out.append((f"Start-up, median of {s.get('runs', '?')}", ["command", "ms", "x"], body))
    body = [[n, _f(v, ".2f", f" {a}"), _met(m)] for n, v, a, m in targets(r)]
    out.append(("Targets: UPS against the floors and peers measured in this same run (each "
                "target says what it compares; met, MISSED, or not measured when a part did "
                "not run)", ["target", "measured", "met"], body))  # fmt: skip
    return out


def _paper_rows(r: dict[str, Any]) -> list[list[str]]:
    rows: list[list[str]] = []
    can = r.get("can_latency") or {}
    floor = (r.get("floors") or {}).get("python_can_recv_us")
    for n, ours in (r.get("local_notify_us") or {}).items():
        p99 = can.get("local_notify_us", {}).get(n, {}).get("p99")
        paper = PAPER["local_notify_us"][n]
        rows.append([f"local notification, {n} subscriber(s)", f"{ours:.0f}", _f(p99),
                     _f(floor), _x(ours, floor), f"{paper}", _x(ours, paper)])  # fmt: skip
    if r.get("publish_latency_us"):
        ours, paper = r["publish_latency_us"], PAPER["publish_latency_us"]
        p99 = can.get("publish_latency_us", {}).get("p99")
        rows.append(["publish -> frame on the bus", f"{ours:.0f}", _f(p99), "-", "-",
                     f"{paper:.0f}", _x(ours, paper)])  # fmt: skip
    floors = r.get("floors") or {}
    floor_of = {
        "tcp_same_host": floors.get("raw_tcp_rtt_us"),
        "can_can": floors.get("raw_can_rtt_us"),
    }
    for key, value in (r.get("rtt_us") or {}).items():
        fl = (floor_of.get(key) or {}).get("p50")
        paper = PAPER["rtt_us"].get(key)
        label = f"round trip, {RTT_LABELS.get(key, key)}"
        rows.append([label, f"{value['p50']:.0f}", f"{value['p99']:.0f}", _f(fl),
                     _x(value["p50"], fl), _f(paper), _x(value["p50"], paper)])  # fmt: skip
    for label, size in (r.get("code_size") or {}).items():
        kb = PAPER["code_kb"].get(label)
        rows.append([f"code: {label}", f"{size['kb']} KB", f"{size['lines']} lines", "-", "-",
                     f"{kb} KB" if kb else "-", _x(size["kb"], kb)])  # fmt: skip
    return rows


# --- text and Markdown -----------------------------------------------------------------------


def _machine_line(r: dict[str, Any]) -> str:
    m = r["machine"]
    packages = ", ".join(f"{k} {v}" for k, v in (m.get("packages") or {}).items() if v)
    return (
        f"ups bench ({'quick' if m['quick'] else 'full'}, {m.get('seconds', '?')} s): "
        f"{m['cpu']}, {m['cpus']} CPUs, Linux {m['kernel']}, Python {m['python']}, "
        f"{m['date']}; {packages}; mosquitto {m.get('mosquitto') or '-'}"
    )


def _skips(r: dict[str, Any]) -> list[str]:
    lines = [f"note: {n}" for n in r.get("notes", [])]
    lines += [f"skipped {k}: {why}" for k, why in r.get("skipped", {}).items()]
    lines += [f"FAILED {k}: {why.splitlines()[0] if why else ''}" for k, why in r["failed"].items()]
    return lines


def text(r: dict[str, Any]) -> str:
    """The tables, as the terminal shows them."""
    lines = [_machine_line(r), "", *aligned(tables(r))]
    return "\n".join(lines + _skips(r)).rstrip() + "\n"


def markdown(r: dict[str, Any], images: list[str]) -> str:
    """report.md: the machine, every table, what the figures are, the plots."""
    m = r["machine"]
    md = ["# ups bench", "", f"{'Quick' if m['quick'] else 'Full'} run of {m['date']}, "
          f"{m.get('seconds', '?')} s.", "", "## Machine", ""]  # fmt: skip
    md += [f"- CPU: {m['cpu']}, {m['cpus']} CPUs; Linux {m['kernel']}; Python {m['python']}"]
    md += [f"- {k}: {v or 'not installed'}" for k, v in (m.get("packages") or {}).items()]
    md += [f"- mosquitto: {m.get('mosquitto') or 'not installed'}; run as root: {m.get('root')}"]
    md.append("")
    for title, head, rows in tables(r):
        md += [f"## {title}", "", "| " + " | ".join(head) + " |"]
        md += ["| " + " | ".join("---" for _ in head) + " |"]
        md += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows]
        md.append("")
    md += ["## What is measured", "", *[f"- {n}" for n in NOTES], ""]
    skips = _skips(r)
    if skips:
        md += ["## Not measured in this run", "", *[f"- {s}" for s in skips], ""]
    if images:
        md += ["## Plots", "", *[f"![{name}]({name})" for name in images], ""]
    elif importlib.util.find_spec("matplotlib") is None:
        from ups._extras import install_hint

        md += [f"No plots: matplotlib is not installed ({install_hint('bench')}).", ""]
    return "\n".join(md)


def write(r: dict[str, Any], where: Path) -> None:
    """report.md, results.json and PNG plots in ``where``."""
    where.mkdir(parents=True, exist_ok=True)
    (where / "results.json").write_text(json.dumps(r, indent=1, default=str))
    images = plots(r, where, PAPER)
    (where / "report.md").write_text(markdown(r, images))
