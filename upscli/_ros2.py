"""``ups ros2``: its arguments here (cheap to build: ``--help`` imports nothing of the ``ros2``
package), its work in ``ros2`` (imported when it runs)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from ups._cliargs import add_catalog, add_network, positive_float, run_until_signal
from ups._errors import ConfigError

from ._argparsing import add_metrics

HELP = "UPS channels as ROS 2 topics through rmw_zenoh (no ROS needed); or check a map"


def add_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    cmd = command("ros2", help=HELP)
    cmd.add_argument("--map", metavar="FILE", help="the map of ROS 2 topics onto UPS channels")
    cmd.add_argument(
        "--ros", metavar="ENDPOINT", default="tcp/localhost:7447",
        help="the ROS 2 system's Zenoh router, rmw_zenohd (default tcp/localhost:7447)",
    )  # fmt: skip
    cmd.add_argument("--ros-config", metavar="FILE", default=None,
                     help="a Zenoh config file for the ROS 2 side (TLS, ...)")  # fmt: skip
    cmd.add_argument(
        "--domain", type=domain, default=None,
        help="the ROS domain id (default: the map's, $ROS_DOMAIN_ID, else 0)",
    )  # fmt: skip
    add_network(cmd, "the robot's CAN bus", "the robot's IP network")
    cmd.add_argument("--node-id", type=lambda t: int(t, 0), default=None, help="64-bit node id")
    cmd.add_argument("--timeout", type=positive_float, default=30.0, help="seconds to join")
    add_metrics(cmd)
    actions = cmd.add_subparsers(dest="ros2_command", required=False, metavar="ACTION")
    act = actions.add_parser("check", help="check a map; exit 2 naming the line")
    act.add_argument("file", metavar="FILE", help="the map (TOML), e.g. examples/robot.ros2.toml")
    add_catalog(act)
    cmd.set_defaults(run=_run)


def domain(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text}") from None
    if not 0 <= value <= 232:
        raise argparse.ArgumentTypeError(f"a ROS domain id is 0-232, not {value}")
    return value


def _run(args: argparse.Namespace) -> int:
    from ups._extras import require

    for module in ("rosbags", "xxhash") if args.ros2_command else ("rosbags", "xxhash", "zenoh"):
        require(module, "ros2", f"ups ros2 needs {module}, which is not installed")
    from ups.ros2._mapping import load_map

    if args.ros2_command is None:
        if args.map is None:
            raise ConfigError("ups ros2 needs --map FILE (or: ups ros2 check FILE)")
        bridge = load_map(args.map, domain=args.domain)
        from ups.ros2._serve import serve

        return run_until_signal(serve(args, bridge))
    from ups._catalog import Catalog

    catalog = Catalog.load(args.catalog) if args.catalog else None
    bridge = load_map(args.file, catalog, domain=args.domain)
    for t in bridge.topics:
        fields = ", ".join(f"{f.ros}<->{f.ups}" for f in t.fields)
        print(f"{t.topic} ({t.type}, {t.direction}) on {t.channel.channel}: {fields}")
        print(f"  key {t.key}")
    return 0
