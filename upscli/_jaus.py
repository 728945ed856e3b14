"""``ups jaus`` and ``ups jaus-ocu``: their arguments here (cheap to build: ``--help`` imports
nothing of the ``jaus`` package), their work in ``jaus`` (imported when they run)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from ups._cliargs import (
    add_catalog,
    add_network,
    positive_float,
    positive_int,
    run_until_signal,
)
from ups._errors import ConfigError

from ._argparsing import add_metrics

OCU_HELP = "a small JAUS operator control unit: discover, query, control, send, watch, waypoints"


def add_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    cmd = command("jaus", help="a JAUS component on a UPS node (JUDP and RA 3.3); or check a "
                  "mapping")  # fmt: skip
    cmd.add_argument(
        "--listen", default="127.0.0.1:3794", metavar="HOST:PORT",
        help="where JAUS OCUs reach the component (UDP; default 127.0.0.1:3794, JUDP's port)",
    )  # fmt: skip
    cmd.add_argument(
        "--id", default="1.1.1", metavar="S.N.C",
        help="the component's JAUS id: subsystem.node.component (default 1.1.1)",
    )  # fmt: skip
    cmd.add_argument("--map", metavar="FILE", help="the mapping of JAUS messages onto channels")
    cmd.add_argument("--name", default="UPS robot", help="what Report Identification says")
    cmd.add_argument(
        "--authority", type=authority, default=0, metavar="0-255",
        help="the lowest authority an OCU needs to take control (default 0)",
    )  # fmt: skip
    add_network(cmd, "the robot's CAN bus", "the robot's IP network")
    cmd.add_argument("--node-id", type=lambda t: int(t, 0), default=None, help="64-bit node id")
    cmd.add_argument("--timeout", type=positive_float, default=30.0, help="seconds to join")
    add_metrics(cmd)
    jaus_commands = cmd.add_subparsers(dest="jaus_command", required=False, metavar="ACTION")
    act = jaus_commands.add_parser(
        "check", help="check a mapping of JAUS messages onto UPS channels; exit 2 naming the line"
    )
    act.add_argument(
        "file", metavar="FILE", help="the mapping (TOML), e.g. examples/robot.jaus.toml"
    )
    add_catalog(act)
    cmd.set_defaults(run=_run_jaus)

    cmd = command("jaus-ocu", help=OCU_HELP)
    _add_ocu_arguments(cmd)
    cmd.set_defaults(run=_run_ocu)


def authority(text: str) -> int:
    """A JAUS authority code: 0-255."""
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text}") from None
    if not 0 <= value <= 255:
        raise argparse.ArgumentTypeError(f"an authority is 0-255, not {value}")
    return value


def _add_ocu_arguments(cmd: argparse.ArgumentParser) -> None:
    where = cmd.add_mutually_exclusive_group()
    where.add_argument("--target", metavar="HOST:PORT", help="the component's UDP address")
    where.add_argument(
        "--broadcast", metavar="ADDRESS", default=None,
        help="without --target: ask by broadcast to ADDRESS:3794 only (default: "
        "255.255.255.255:3794 and this host's 127.0.0.1:3794); the first to answer is used",
    )  # fmt: skip
    cmd.add_argument("--to", metavar="S.N.C", help="the component's JAUS id (default: anyone)")
    cmd.add_argument("--id", default="200.1.1", metavar="S.N.C", help="this OCU's JAUS id")
    cmd.add_argument("--framing", choices=("judp", "ra33"), default="judp",
                     help="JUDP (AS5669A, default) or paper 001's RA 3.3 framing")  # fmt: skip
    cmd.add_argument("--timeout", type=positive_float, default=2.0,
                     help="seconds to wait for answers (default 2)")  # fmt: skip
    actions = cmd.add_subparsers(dest="ocu_command", required=True, metavar="ACTION")
    actions.add_parser("discover", help="who answers Query Identification (broadcast)")
    act = actions.add_parser("query", help="ask for a report: GlobalPose, Status, Control...")
    act.add_argument("message", metavar="MESSAGE")
    act = actions.add_parser("control", help="request, release or query control")
    act.add_argument("action", choices=("request", "release", "query"))
    act.add_argument("--authority", type=authority, default=10, help="0-255 (default 10)")
    act = actions.add_parser("send", help="send a command: MESSAGE FIELD=VALUE ...")
    act.add_argument("message", metavar="MESSAGE", help="e.g. SetWrenchEffort")
    act.add_argument("fields", nargs="*", metavar="FIELD=VALUE")
    act.add_argument("--control", action="store_true",
                     help="take control and resume first, release after")  # fmt: skip
    act.add_argument(
        "--hold", type=positive_float, default=None, metavar="SECONDS",
        help="with --control: keep control SECONDS after sending (Ctrl-C lets go sooner)",
    )  # fmt: skip
    act.add_argument("--authority", type=authority, default=10, help="0-255 (default 10)")
    act = actions.add_parser("watch", help="an event subscription: each report as it comes")
    act.add_argument("message", metavar="MESSAGE", help="e.g. GlobalPose")
    act.add_argument("--rate", type=positive_float, default=1.0,
                     help="reports per second (default 1)")  # fmt: skip
    act.add_argument("--change", action="store_true", help="on every change, not periodic")
    act.add_argument("--count", type=positive_int, default=None,
                     help="stop after COUNT reports")  # fmt: skip
    act = actions.add_parser(
        "waypoints", help="load a local waypoint list, execute it, follow it to its end"
    )
    act.add_argument("points", nargs="+", metavar="X,Y", help="waypoints in metres, in order")
    act.add_argument("--speed", type=positive_float, default=1.0, help="m/s (default 1)")
    act.add_argument(
        "--tolerance",
        type=positive_float,
        default=None,
        help="metres from a waypoint that count as reached (default: the robot's)",
    )
    act.add_argument(
        "--poll",
        type=positive_float,
        default=0.5,
        help="seconds between questions about the active waypoint (default 0.5)",
    )
    act.add_argument("--authority", type=authority, default=10, help="0-255 (default 10)")


def _run_jaus(args: argparse.Namespace) -> int:
    from ups.jaus._mapping import load_mapping

    if args.jaus_command is None:
        if args.map is None:
            raise ConfigError("ups jaus needs --map FILE (or: ups jaus check FILE)")
        bridge = load_mapping(args.map)
        from ups.jaus._serve import serve

        return run_until_signal(serve(args, bridge))
    from ups._catalog import Catalog

    catalog = Catalog.load(args.catalog) if args.catalog else None
    bridge = load_mapping(args.file, catalog)
    for name, entry in bridge.items():
        way = "JAUS -> UPS" if entry.command else "UPS -> JAUS"
        fields = ", ".join(f"{f.jaus}->{f.ups}" for f in entry.fields)
        stamp = ", time stamp: the event's" if entry.stamped else ""
        print(f"{name}: {way} on {entry.channel.channel} ({fields}{stamp})")
    if bridge.authority is not None:
        ranges = ", ".join(f"{net} at most {cap}" for net, cap in bridge.authority.ranges)
        print(f"authority: {ranges}; any other address: no control")
    return 0


def _run_ocu(args: argparse.Namespace) -> Any:
    from ups.jaus._ocu import run

    return run(args)
