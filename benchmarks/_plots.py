"""The PNG plots of ``ups bench --report``: round trips against the peers, fan-out, payload
sizes, local notification against the paper. Drawn with matplotlib (the bench extra) when it
is installed; without it there are none, and the report says so."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any


def plots(r: dict[str, Any], where: Path, paper: dict[str, Any]) -> list[str]:
    """The file names of the plots written into ``where`` (none without matplotlib)."""
    if importlib.util.find_spec("matplotlib") is None:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made: list[str] = []

    def save(fig: Any, name: str) -> None:
        fig.tight_layout()
        fig.savefig(where / name, dpi=100)
        plt.close(fig)
        made.append(name)

    rows = {
        k: v for k, v in r.get("tcp_compare", {}).get("rows", {}).items() if v.get("rtt_p50_us")
    }
    if rows:
        fig, ax = plt.subplots(figsize=(8, 4))
        labels = list(rows)
        colors = ["tab:red" if k.startswith("UPS") else "tab:blue" for k in labels]
        ax.barh(labels, [v["rtt_p50_us"] for v in rows.values()], color=colors)
        ax.invert_yaxis()
        ax.set_xlabel("round trip p50 (µs), 8 B, loopback, both sides pinned to one CPU")
        save(fig, "rtt.png")
    fan = r.get("fanout") or []
    if fan:
        fig, ax = plt.subplots(figsize=(6, 4))
        n = [row["subscribers"] for row in fan]
        ax.plot(n, [row["ups"]["total_msgs_per_s"] for row in fan], "o-", label="UPS")
        if all((row.get("zmq") or {}).get("total_msgs_per_s") for row in fan):
            ax.plot(n, [row["zmq"]["total_msgs_per_s"] for row in fan], "s-", label="pyzmq HWM=0")
        ax.set_xscale("log", base=2)
        ax.set(xlabel="subscriber processes", ylabel="deliveries/s in all, lossless")
        ax.legend()
        save(fig, "fanout.png")
    sizes = r.get("payload") or []
    if sizes:
        fig, ax = plt.subplots(figsize=(6, 4))
        x = [row["size"] for row in sizes]
        ax.plot(x, [row["ups"]["mb_per_s"] for row in sizes], "o-", label="UPS")
        ax.plot(x, [row["raw_tcp"]["mb_per_s"] for row in sizes], "s-", label="raw TCP")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set(xlabel="payload (bytes)", ylabel="MB/s one way")
        ax.legend()
        save(fig, "payload.png")
    notify = r.get("local_notify_us") or {}
    if notify:
        fig, ax = plt.subplots(figsize=(6, 4))
        n = list(notify)
        ax.plot(n, list(notify.values()), "o-", label="UPS today (p50)")
        floor = (r.get("floors") or {}).get("python_can_recv_us")
        if floor:
            ax.axhline(floor, linestyle=":", color="gray", label="python-can recv (floor, p50)")
        ax.plot(n, [paper["local_notify_us"][k] for k in n], "s--", label="paper (RTLinux avg)")
        ax.set(xlabel="local subscribers", ylabel="µs, frame arrival -> all notified")
        ax.legend()
        save(fig, "local_notify.png")
    return made
