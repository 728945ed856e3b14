"""``ups ethercat``: its arguments here (cheap to build: ``--help`` imports nothing of the
``ethercat`` package nor pysoem), its work in ``ethercat`` (imported when it runs)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable

from ups._errors import ConfigError

HELP = "EtherCAT: list the slaves of a segment (the master side, with pysoem)"


def add_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    cmd = command("ethercat", help=HELP)
    actions = cmd.add_subparsers(dest="ethercat_command", required=False, metavar="ACTION")
    act = actions.add_parser("scan", help="list the slaves: identity, state, process data sizes")
    act.add_argument(
        "--ifname", required=True, metavar="IF",
        help="the network interface of the EtherCAT segment (needs root or CAP_NET_RAW)",
    )  # fmt: skip
    act.add_argument("--json", action="store_true", help="one JSON list instead of a table")
    cmd.set_defaults(run=_run)


def _run(args: argparse.Namespace) -> int:
    from ups._extras import require

    require("pysoem", "ethercat", "ups ethercat needs pysoem, which is not installed")
    if args.ethercat_command != "scan":
        raise ConfigError("ups ethercat: only 'ups ethercat scan --ifname IF' is built yet")
    from ups.ethercat import scan

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
