"""``ups monitor``: a live terminal view of a network, in the spirit of ``top``.

Channels with their rate, count, last value (decoded by the catalog) and publishers; nodes
joining, falling silent and leaving; drops, foreign frames and, on CAN, the bus load. On a
terminal it redraws in place (rich); otherwise, or with ``--plain``, it prints a text
snapshot every ``--interval`` seconds, or one JSON object per line with ``--json``. Ctrl-C
(SIGINT, SIGTERM) or ``--duration`` stops it, the terminal as it was. On CAN it only listens.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from .._cliargs import (
    add_catalog,
    add_network,
    add_tls,
    channel_arg,
    positive_float,
    positive_int,
    run_until_signal,
)
from .._errors import BrokerUnavailable
from ._net import network_of

if TYPE_CHECKING:
    from ._net import IpNetwork

HELP = "a live view of a network: channels, rates, last values, nodes, drops, bus load"


def add_arguments(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument(
        "channels", nargs="*", type=channel_arg, metavar="CHANNEL",
        help="TCP/IP: watch only these (default: every channel the TCP-ECB lists)",
    )  # fmt: skip
    add_network(cmd, "watch a CAN bus (listening only)", "watch an IP network")
    cmd.add_argument("--db", default=None, help="CAN: the CAN-ECB's database (default: the bus's)")
    add_catalog(cmd)
    cmd.add_argument(
        "--bitrate", type=positive_int, default=500_000,
        help="CAN: the bus's bit rate, for its load (default 500000)",
    )  # fmt: skip
    cmd.add_argument("--interval", type=positive_float, default=1.0, help="seconds per refresh")
    cmd.add_argument("--duration", type=positive_float, default=None, help="stop after S seconds")
    view = cmd.add_mutually_exclusive_group()
    view.add_argument("--plain", action="store_true", help="text snapshots, not a live screen")
    view.add_argument("--json", action="store_true", help="one JSON snapshot per line")
    cmd.add_argument("--timeout", type=positive_float, default=5.0, help="seconds to wait")
    add_tls(cmd, node=True)


def run(args: argparse.Namespace) -> int:
    from .._bindings import Bindings
    from .._catalog import load_catalog
    from ._live import Live

    can, net = network_of(args)
    catalog = load_catalog(args.catalog)
    live = Live(catalog, net.label if net else "can", can or str(net), args.bitrate)
    bindings = Bindings()
    if can is not None:
        bindings.load_bus_db(can, args.db)
    screen = not (args.plain or args.json) and sys.stdout.isatty()
    if screen:
        from .._extras import require

        require("rich", "tools", "the live screen needs rich, which is not installed",
                " (or give --plain)")  # fmt: skip
    return run_until_signal(_watch(args, live, bindings, can, net, screen))


async def _watch(
    args: argparse.Namespace, live: Any, bindings: Any, can: str | None, net: IpNetwork | None,
    screen: bool,
) -> int:  # fmt: skip
    import asyncio
    import json

    from ._live import feed_can, feed_tcp

    joined = can is not None  # on CAN, listening needs nobody's answer

    async def feed() -> None:
        nonlocal joined
        if can is not None:
            await feed_can(live, can, bindings)
            return
        assert net is not None
        async with net.node("ups-monitor") as node:
            joined = True
            await feed_tcp(live, node, net, [c.uid for c in args.channels])

    feeder = asyncio.create_task(feed())
    loop = asyncio.get_running_loop()
    deadline = None if args.duration is None else loop.time() + args.duration
    display = _Screen() if screen else None
    try:
        while deadline is None or loop.time() < deadline:
            wait = args.interval if deadline is None else min(args.interval,
                                                              deadline - loop.time())  # fmt: skip
            done, _ = await asyncio.wait({feeder}, timeout=max(0.0, wait))
            if done:
                feeder.result()  # the feed failed (the TCP-ECB went away ...): say so
            snap = live.snapshot()
            if display is not None:
                display.show(snap)
            elif args.json:
                print(json.dumps(snap), flush=True)
            else:
                print(render(snap), flush=True)
    except asyncio.CancelledError:
        pass  # Ctrl-C: the way to stop it
    finally:
        if display is not None:
            display.close()
        feeder.cancel()
        await asyncio.gather(feeder, return_exceptions=True)
    if not joined and deadline is not None and loop.time() >= deadline:  # empty tables: say why
        assert net is not None
        raise BrokerUnavailable(f"nothing answered at {net.where} within --duration "
                                f"{args.duration:g} s: the tables above are empty")  # fmt: skip
    return 0


class _Screen:
    """The live screen: rich redraws one table in place, and puts the terminal back."""

    def __init__(self) -> None:
        from rich.console import Console
        from rich.live import Live as RichLive

        self._live = RichLive(console=Console(), auto_refresh=False, transient=False)
        self._live.start()

    def show(self, snap: dict[str, Any]) -> None:
        from rich.console import Group
        from rich.table import Table
        from rich.text import Text

        channels = Table(title=_title(snap), title_justify="left", expand=True)
        for column in ("CHANNEL", "ETAG", "RATE/S", "COUNT", "LAST VALUE", "AGE S", "FROM"):
            channels.add_column(column, overflow="fold")
        for c in snap["channels"]:
            channels.add_row(c["name"] or c["key"], c["etag"] or "-", str(c["rate"]),
                             str(c["count"]), c["last"], str(c["age"]),
                             ", ".join(c["publishers"][:3]))  # fmt: skip
        nodes = Table(expand=True)
        for column in ("NODE", "TXNODE / ADDRESS", "NAME", "STATE"):
            nodes.add_column(column)
        for n in snap["nodes"]:
            nodes.add_row(n["key"], n["txnode"] or n["address"] or "-", n["name"] or "-",
                          "up" if n["alive"] else "gone")  # fmt: skip
        recent = Text("\n".join(snap["recent"][-5:]) or "(no joins or leaves yet)")
        self._live.update(Group(channels, nodes, recent), refresh=True)

    def close(self) -> None:
        self._live.stop()


def _title(snap: dict[str, Any]) -> str:
    counters = snap["counters"]
    parts = [f"ups monitor  {snap['network']} {snap['source']}"]
    if snap["bus_load"] is not None:
        parts.append(f"bus load {snap['bus_load']:.1%}")
    parts.append(f"dropped {counters['dropped']}")
    parts.append(f"foreign {counters['foreign']}, malformed {counters['malformed']}")
    if counters["untracked"]:
        parts.append(f"untracked {counters['untracked']}")
    return "  |  ".join(parts)


def render(snap: dict[str, Any]) -> str:
    """A snapshot as plain text: a title, the channels, the nodes, who came and went."""
    from .ls import _aligned

    rows: list[tuple[str, ...]] = [
        ("CHANNEL", "ETAG", "RATE/S", "COUNT", "LAST VALUE", "AGE S", "FROM")
    ]
    rows += [
        (c["name"] or c["key"], c["etag"] or "-", str(c["rate"]), str(c["count"]), c["last"],
         str(c["age"]), ", ".join(c["publishers"][:3]) or "-")
        for c in snap["channels"]
    ]  # fmt: skip
    node_rows: list[tuple[str, ...]] = [("NODE", "TXNODE / ADDRESS", "NAME", "STATE")]
    node_rows += [
        (n["key"], n["txnode"] or n["address"] or "-", n["name"] or "-",
         "up" if n["alive"] else "gone")
        for n in snap["nodes"]
    ]  # fmt: skip
    lines = [_title(snap), *_aligned(rows), "", *_aligned(node_rows)]
    lines += [f"  {line}" for line in snap["recent"][-5:]]
    return "\n".join(lines) + "\n"
