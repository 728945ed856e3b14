"""``ups ethercat``: its arguments here (cheap to build: ``--help`` imports nothing of the
``ethercat`` package nor pysoem), its work in ``ethercat`` (imported when it runs)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from ups._cliargs import add_network, positive_float, run_until_signal
from ups._errors import ConfigError

HELP = "EtherCAT: the master of a segment on a UPS node (pysoem); or scan it, or check a map"


def add_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    cmd = command("ethercat", help=HELP)
    cmd.add_argument(
        "--ifname", metavar="IF",
        help="the network interface of the EtherCAT segment (needs root or CAP_NET_RAW)",
    )  # fmt: skip
    cmd.add_argument("--map", metavar="FILE", help="the map of channels onto process data")
    cmd.add_argument(
        "--cycle", type=positive_float, default=None, metavar="MS",
        help="milliseconds between two process-data exchanges (default: the map's cycle)",
    )  # fmt: skip
    add_network(cmd, "the robot's CAN bus", "the robot's IP network")
    cmd.add_argument("--node-id", type=lambda t: int(t, 0), default=None, help="64-bit node id")
    cmd.add_argument("--timeout", type=positive_float, default=30.0, help="seconds to join")
    actions = cmd.add_subparsers(dest="ethercat_command", required=False, metavar="ACTION")
    act = actions.add_parser("scan", help="list the slaves: identity, state, process data sizes")
    act.add_argument(
        "--ifname", required=True, metavar="IF",
        help="the network interface of the EtherCAT segment (needs root or CAP_NET_RAW)",
    )  # fmt: skip
    act.add_argument("--json", action="store_true", help="one JSON list instead of a table")
    act = actions.add_parser("check", help="check a map; exit 2 naming the line")
    act.add_argument(
        "file", metavar="FILE", help="the map (TOML), e.g. examples/robot.ethercat.toml"
    )
    cmd.set_defaults(run=_run)


def _run(args: argparse.Namespace) -> int:
    from ups._extras import require

    if args.ethercat_command == "check":
        return _check(args.file)
    require("pysoem", "ethercat", "ups ethercat needs pysoem, which is not installed")
    if args.ethercat_command == "scan":
        return _scan(args)
    if args.ifname is None or args.map is None:
        raise ConfigError("ups ethercat needs --ifname IF and --map FILE (or: scan, check)")
    from ups.ethercat._map import MAX_CYCLE, MIN_CYCLE, load_map
    from ups.ethercat._serve import serve

    if args.cycle is not None and not MIN_CYCLE <= args.cycle / 1000 <= MAX_CYCLE:
        raise ConfigError(
            f"--cycle: at least {MIN_CYCLE * 1000:g} ms and at most {MAX_CYCLE * 1000:g} ms"
        )
    return run_until_signal(serve(args, load_map(args.map)))


def _check(path: str) -> int:
    from ups.ethercat._map import load_map

    emap = load_map(path)
    print(f"cycle {emap.cycle * 1000:g} ms, outputs safe after {emap.timeout:g} s of silence, "
          f"status on {emap.status}")  # fmt: skip
    for slave in emap.slaves.values():
        print(f"slave {slave.position}: {slave.identity()}")
        for o in slave.outputs:
            print(f"  output byte {o.byte} ({o.type}) <- {o.spec.channel}.{o.field}")
    for channel in emap.inputs:
        when = f"every {channel.every} cycle(s)" if channel.every else "on change"
        for e in channel.entries:
            print(f"  slave {e.slave} input byte {e.byte} ({e.type}) -> "
                  f"{channel.spec.channel}.{e.field}, {when}")  # fmt: skip
    return 0


def _scan(args: argparse.Namespace) -> int:
    import json

    from ups.ethercat import scan

    if args.ifname is None:
        raise ConfigError("ups ethercat scan needs --ifname IF")
    slaves = scan(args.ifname)
    if args.json:
        print(json.dumps([s.as_json() for s in slaves], indent=1))
        return 0
    print(f"{'pos':>3}  {'vendor':10}  {'product':10}  {'revision':10}  {'state':13}  "
          f"{'out':>3}  {'in':>3}  name")  # fmt: skip
    for s in slaves:
        print(f"{s.position:>3}  0x{s.vendor:08x}  0x{s.product:08x}  0x{s.revision:08x}  "
              f"{s.state:13}  {s.outputs:>3}  {s.inputs:>3}  {s.name}")  # fmt: skip
    return 0
