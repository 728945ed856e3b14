"""The ``ups`` command: daemons, publishing and subscribing from a shell, the demo.

This package sits above every other package of the project: the library (``ups``) knows
nothing of it, nor of ``broker``, ``gateway``, ``jaus``, ``examples`` and ``benchmarks``,
which it imports lazily, per subcommand, so that each command pays only for its own imports.
``ups`` is ``main`` (the console script); ``python -m upscli`` runs it too.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import re
import sys
from typing import Any

from ups import tools
from ups._address import DEFAULT_PORT
from ups._cliargs import (
    add_can,
    add_catalog,
    add_tls,
    add_zenoh,
    add_zenoh_config,
    explained,
    nonnegative_float,
    positive_float,
    positive_int,
    run_until_signal,
    tls_of,
    warn_if_virtual,
)
from ups._errors import ConfigError, UpsError

from ._argparsing import Unbuilt, Version, add_ecb_service, add_metrics, unrecognized

EXIT_USAGE = 2
#: log at INFO; the other commands at WARNING
DAEMONS = ("can-broker", "c-ecb", "broker", "gateway", "zenoh-router", "jaus", "ros2")


#: the operators' tools (``ups/tools/``, a module each) and their lines in ``ups --help``: a
#: tool's module is imported only when it is the command (``console``'s loads its web guard
#: and the metrics); tests/test_cli_behaves.py holds each line equal to its module's ``HELP``
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), "")  # the command, if any
    parser = _parser(only=chosen)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the command's own usage, not the top level's, and the option meant
        unrecognized(parser, args, unknown)
    import logging  # after parsing: --help does without it

    quiet = args.command not in DAEMONS  # a daemon logs what it does; a command says it
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING if quiet else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        result: int = args.run(args)
        return result
    except UpsError as exc:
        print(f"ups {args.command}: {explained(args, exc)}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # the reader of our output went away: a way to stop, not an error
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # a port in use, an address that does not exist, a full disk ...
        text = re.sub(r"^\[Errno -?\d+\] ", "", str(exc))
        print(f"ups {args.command}: {text}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


def _parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command line; with ``only``, every command is listed but only that one's options
    are built (the others are not needed to parse, and ``ups analyze``'s need the real-time
    analysis, the heaviest import)."""
    parser = argparse.ArgumentParser(
        prog="ups", description=__doc__.splitlines()[0].replace("``", "")
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug detail")
    parser.add_argument("--version", action=Version)
    common = argparse.ArgumentParser(add_help=False)  # -v after the command works too
    common.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                        help="log debug detail")  # fmt: skip
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, **kwargs: Any) -> argparse.ArgumentParser:
        if only is not None and name != only:
            commands.add_parser(name, help=kwargs.get("help"))
            return Unbuilt()  # type: ignore[return-value]
        return commands.add_parser(name, parents=[common], **kwargs)

    cmd = command("can-broker", help="run the CAN-ECB of one bus")
    add_can(cmd)
    cmd.add_argument(
        "--db", default=None,
        help="SQLite file of TxNodes and etags (default: the bus's own file under "
        "$UPS_STATE_DIR, $XDG_STATE_HOME/ups or ~/.local/state/ups)",
    )  # fmt: skip
    cmd.add_argument(
        "--recovery", type=nonnegative_float, default=2.0,
        help="seconds after start spent relearning the bus before answering (default 2)",
    )  # fmt: skip
    cmd.add_argument(
        "--max-channels", type=positive_int, default=8192,
        help="channels one node may subscribe to or publish on (default 8192)",
    )  # fmt: skip
    cmd.add_argument(
        "--lease", type=positive_float, default=86_400.0,
        help="seconds after which a silent node's TxNode, or an unused etag, may be given to "
        "another when none is free (default 86400)",
    )  # fmt: skip
    add_ecb_service(cmd)
    cmd.set_defaults(run=_run_can_broker)

    cmd = command("broker", help="run a TCP-ECB (the registry of a TCP/IP network)")
    cmd.add_argument(
        "--listen", default=f"127.0.0.1:{DEFAULT_PORT}", metavar="HOST:PORT",
        help=f"address to listen on (default 127.0.0.1:{DEFAULT_PORT}; 0.0.0.0 for every one)",
    )  # fmt: skip
    cmd.add_argument(
        "--liveness", type=positive_float, default=3.0,
        help="seconds a silent or disconnected node stays registered (default 3)",
    )  # fmt: skip
    cmd.add_argument(
        "--recovery", type=nonnegative_float, default=1.5,
        help="seconds after start to collect re-registrations before answering (default 1.5)",
    )  # fmt: skip
    cmd.add_argument(
        "--acl", metavar="FILE", default=None,
        help="TOML access control list: [identity.NAME] publish/subscribe = [channels, globs, "
        "0xUIDs], status = true, node_ids = [0xIDs]; needs TLS; an identity not listed may do "
        "nothing",
    )  # fmt: skip
    cmd.add_argument(
        "--identities", metavar="FILE", default=None,
        help="with TLS: the file that keeps which identity each node id belongs to, across "
        "restarts (default: tcp-ecb-HOST_PORT-identities.json under $UPS_STATE_DIR, "
        "$XDG_STATE_HOME/ups or ~/.local/state/ups; none on port 0)",
    )  # fmt: skip
    add_tls(cmd)
    add_metrics(cmd)
    cmd.set_defaults(run=_run_broker)

    cmd = command("gateway", help="forward subscribed events between a CAN bus and TCP/IP or Zenoh")
    add_can(cmd)
    ip_side = cmd.add_mutually_exclusive_group()
    ip_side.add_argument("--broker", metavar="HOST:PORT", help="the TCP-ECB (default: $UPS_BROKER)")
    add_zenoh(ip_side)
    add_zenoh_config(cmd)
    cmd.add_argument(
        "--listen", metavar="HOST:PORT", default=None,
        help="where TCP publishers and 'ups status' reach the gateway (default: any port)",
    )  # fmt: skip
    cmd.add_argument(
        "--db", default=None,
        help="SQLite file of the hosted CAN-ECB's tables (default: the bus's own, as can-broker)",
    )  # fmt: skip
    cmd.add_argument(
        "--external-can-ecb", action="store_true",
        help="do not host the bus's CAN-ECB: one already runs ('ups can-broker')",
    )  # fmt: skip
    cmd.add_argument(
        "--recovery", type=nonnegative_float, default=None,
        help="seconds the hosted CAN-ECB spends relearning the bus after start, as can-broker's "
        "(default 2)",
    )  # fmt: skip
    cmd.add_argument(
        "--bitrate", type=positive_int, default=500_000,
        help="the bus's bit rate: TCP->CAN pacing and real-time admission (default 500000)",
    )  # fmt: skip
    cmd.add_argument("--node-id", type=lambda t: int(t, 0), default=None, help="64-bit node id")
    cmd.add_argument(
        "--join-timeout", type=positive_float, default=30.0, metavar="S",
        help="wait up to S seconds for the CAN-ECB (with --external-can-ecb) and the TCP-ECB or "
        "Zenoh router, also ones not started yet (default 30)",
    )  # fmt: skip
    add_catalog(cmd, "channel names, given on the IP side to the bus's channels (so patterns "
                "there match them)")  # fmt: skip
    add_tls(cmd, node=True)
    add_metrics(cmd)
    cmd.set_defaults(run=_run_gateway)

    cmd = command("status", help="print the tables and counters of a TCP daemon, or of every "
                  "UPS node and gateway on Zenoh")  # fmt: skip
    cmd.add_argument("address", metavar="HOST:PORT", nargs="?", help="a TCP-ECB, gateway or node")
    add_zenoh(cmd)
    add_zenoh_config(cmd)
    cmd.add_argument("--timeout", type=positive_float, default=5.0, help="seconds to wait")
    cmd.add_argument("--json", action="store_true", help="the Status as JSON, for a program")
    add_tls(cmd)
    cmd.set_defaults(run=_run_status)

    cmd = command("zenoh-router", help="run a Zenoh router (Zenoh's own), for a UPS Zenoh network")
    cmd.add_argument(
        "--listen", metavar="ENDPOINT", action="append", default=None,
        help="where clients and other routers reach it (default tcp/127.0.0.1:7447; "
        "repeat for several)",
    )  # fmt: skip
    cmd.add_argument(
        "--connect", metavar="ENDPOINT", action="append", default=[],
        help="another router to link with (repeat for several): routers so linked make one "
        "Zenoh network across hosts and sites",
    )  # fmt: skip
    add_zenoh_config(cmd)
    cmd.set_defaults(run=_run_zenoh_router)

    cmd = command("certs", help="make the fleet CA and certificates for TLS")
    certs = cmd.add_subparsers(dest="certs_command", required=True, metavar="ACTION")
    act = certs.add_parser("ca", help="make DIR/ca.crt and DIR/ca.key")
    act.add_argument("dir", metavar="DIR")
    act = certs.add_parser("issue", help="make DIR/NAME.crt and DIR/NAME.key, signed by DIR's CA")
    act.add_argument("dir", metavar="DIR")
    act.add_argument("name", metavar="NAME", help="the identity (the certificate's common name)")
    act.add_argument(
        "--host", action="append", default=[], metavar="HOST",
        help="a DNS name or IP address clients reach its holder at (repeat; e.g. for a Zenoh "
        "router's certificate, which clients check against tls/HOST:PORT)",
    )  # fmt: skip
    cmd.set_defaults(run=_run_certs)

    from . import _pubsub

    _pubsub.add_commands(command)

    for name, line in tools.COMMANDS.items():  # the operators' tools, one module each
        cmd = command(name, help=line)
        if only in (None, name):
            module = importlib.import_module(f"ups.tools.{name}")
            module.add_arguments(cmd)
            cmd.set_defaults(run=module.run)

    from . import _ethercat, _jaus, _ros2

    _jaus.add_commands(command)
    _ros2.add_commands(command)
    _ethercat.add_commands(command)

    from . import _cecb, _cnode

    _cnode.add_commands(command)
    _cecb.add_commands(command)

    cmd = command("analyze", help="CAN response-time analysis of a message set")
    if only in (None, "analyze"):
        from ups.rt import cli as rt_cli

        rt_cli.add_arguments(cmd)
        cmd.set_defaults(run=rt_cli.run)

    cmd = command(
        "demo", help="run the demo robots on a virtual CAN bus, with a gateway to loopback TCP/IP"
    )
    cmd.add_argument(
        "--duration", type=positive_float, default=None,
        help="seconds to run (default 3; with --processes until Ctrl-C)",
    )  # fmt: skip
    cmd.add_argument(
        "--processes", action="store_true",
        help="each robot part a process of its own on a shared bus (--can), for ups monitor, "
        "console, ls and record to watch",
    )  # fmt: skip
    cmd.add_argument(
        "--can", default=os.environ.get("UPS_CAN") or None, metavar="INTERFACE:CHANNEL",
        help="with --processes: a bus processes share, e.g. socketcan:vcan0 (default: $UPS_CAN)",
    )  # fmt: skip
    cmd.add_argument(
        "--listen", default=f"127.0.0.1:{DEFAULT_PORT}", metavar="HOST:PORT",
        help=f"with --processes: the TCP-ECB's address (default 127.0.0.1:{DEFAULT_PORT})",
    )  # fmt: skip
    cmd.add_argument(
        "--jaus", nargs="?", const="127.0.0.1:3794", default=None, metavar="HOST:PORT",
        help="also a JAUS component on the robot (default 127.0.0.1:3794): it prints the "
        "ups jaus-ocu commands to try, and runs until Ctrl-C unless --duration",
    )  # fmt: skip
    cmd.set_defaults(run=_run_demo)

    cmd = command(
        "bench", help="measure everything beside the paper and the peers (pyzmq, MQTT, zenoh)"
    )
    cmd.add_argument("--quick", action="store_true", help="fewer samples (1-2 minutes here)")
    cmd.add_argument("--json", metavar="PATH", help="write every figure as JSON here")
    cmd.add_argument("--report", metavar="DIR", help="write report.md, results.json and plots")
    cmd.set_defaults(run=_run_bench)

    cmd = command("completion", help='print a bash completion script: eval "$(ups completion)"')
    cmd.set_defaults(run=_run_completion)
    return parser


def _run_completion(args: argparse.Namespace) -> int:
    """A bash completion script for every command and its options, made from this parser."""
    parser = _parser()
    commands = next(
        a for a in parser._actions if isinstance(a, argparse._SubParsersAction)
    )  # argparse keeps its subcommands there; there is no public way to list them
    cases = []
    for name, sub in commands.choices.items():
        options = sorted(o for a in sub._actions for o in a.option_strings)
        cases.append(f'        {name}) opts="{" ".join(options)}" ;;')
    script = _COMPLETION.replace("COMMANDS", " ".join(commands.choices)).replace(
        "CASES", "\n".join(cases)
    )
    print(script)
    return 0


_COMPLETION = """\
_ups() {
    local cur=${COMP_WORDS[COMP_CWORD]} command=${COMP_WORDS[1]} opts
    if [ "$COMP_CWORD" -eq 1 ]; then
        COMPREPLY=($(compgen -W "COMMANDS --help --version -v" -- "$cur"))
        return
    fi
    case "$command" in
CASES
        *) opts="" ;;
    esac
    if [[ "$cur" == -* ]]; then
        COMPREPLY=($(compgen -W "$opts" -- "$cur"))
    else
        COMPREPLY=($(compgen -f -- "$cur"))
    fi
}
complete -F _ups ups"""


def _run_can_broker(args: argparse.Namespace) -> int:
    from ups._metrics import check_metrics
    from ups.broker._store import default_db
    from ups.broker.can_ecb import serve

    db = args.db if args.db is not None else default_db(args.can)
    check_metrics(args.metrics)  # before anything starts, or says anything
    warn_if_virtual(args.can)

    async def run() -> int:
        return await serve(
            args.can, db, args.bitrate, status=args.status, metrics=args.metrics,
            recovery=args.recovery, lease=args.lease, max_channels=args.max_channels,
        )  # fmt: skip

    return run_until_signal(run())


def _run_broker(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ups.broker._acl import Acl
    from ups.broker._identities import default_file
    from ups.broker.tcp_ecb import serve

    tls = tls_of(args)
    acl = Acl.load(args.acl) if args.acl is not None else None
    ids = Path(args.identities) if args.identities else default_file(args.listen)

    async def run() -> int:
        await serve(args.listen, args.liveness, args.recovery, tls, acl, args.metrics, ids)
        return 0

    return run_until_signal(run())


def _run_gateway(args: argparse.Namespace) -> int:
    from ups._catalog import load_catalog
    from ups._metrics import check_metrics
    from ups.gateway import Gateway, serve

    broker, zenoh = args.broker, args.zenoh
    if broker is None and zenoh is None and args.zenoh_config is None:
        broker = os.environ.get("UPS_BROKER") or None
        zenoh = None if broker else os.environ.get("UPS_ZENOH") or None
        if broker is None and zenoh is None:
            raise ConfigError("which IP side? give --broker HOST:PORT or --zenoh ENDPOINT "
                              "(or set UPS_BROKER or UPS_ZENOH)")  # fmt: skip
    if args.listen is not None and broker is None:
        raise ConfigError("--listen is for a gateway to TCP/IP (with --broker)")
    if args.external_can_ecb:  # the options of the hosted CAN-ECB: none is hosted
        for option, value in (("--db", args.db), ("--recovery", args.recovery)):
            if value is not None:
                raise ConfigError(f"{option} is for the CAN-ECB the gateway hosts: not with "
                                  "--external-can-ecb")  # fmt: skip
    check_metrics(args.metrics)
    gateway = Gateway(
        args.can,
        broker,
        zenoh=zenoh,
        zenoh_config=args.zenoh_config,
        db=args.db,
        host_can_ecb=not args.external_can_ecb,
        **({} if args.recovery is None else {"recovery": args.recovery}),
        bitrate=args.bitrate,
        node_id=args.node_id,
        listen=args.listen,
        tls=tls_of(args),
        catalog=load_catalog(args.catalog),
        join_timeout=args.join_timeout,
    )
    warn_if_virtual(args.can)

    async def run() -> int:
        await serve(gateway, args.metrics)
        return 0

    return run_until_signal(run())


def _run_certs(args: argparse.Namespace) -> int:
    from ups._tls import issue, make_ca

    if args.certs_command == "ca":
        crt, key = make_ca(args.dir)
    else:
        crt, key = issue(args.dir, args.name, args.host)
    print(f"{crt}\n{key}")
    return 0


def _run_status(args: argparse.Namespace) -> int:
    import json

    if (args.address is None) == (args.zenoh is None and args.zenoh_config is None):
        raise ConfigError("ups status HOST:PORT (a TCP daemon) or ups status --zenoh ENDPOINT")

    async def run() -> int:
        info: Any
        if args.address is None:
            from ups._zenohstatus import query_status as query_zenoh

            info = await query_zenoh(args.zenoh or "", args.zenoh_config, args.timeout)
        else:
            from ups._tcpquery import query_status

            info = await query_status(args.address, args.timeout, tls_of(args))
        if args.json:
            print(json.dumps(info, indent=2))
        else:
            from ups.tools.status import render

            print(render(info))
        return 0

    return run_until_signal(run())


def _run_zenoh_router(args: argparse.Namespace) -> int:
    from ups.broker.zenoh_router import serve

    async def run() -> int:
        await serve(args.listen or ["tcp/127.0.0.1:7447"], args.connect, args.zenoh_config)
        return 0

    return run_until_signal(run())


def _run_bench(args: argparse.Namespace) -> int:
    try:
        from ups.benchmarks import bench
    except ImportError as exc:
        from ups._extras import install_hint

        raise ConfigError(
            f"the benchmarks cannot be loaded ({exc.name or exc} is missing): "
            f"{install_hint('bench')}"
        ) from None
    argv = ["--quick"] if args.quick else []
    argv += ["--json", args.json] if args.json else []
    argv += ["--report", args.report] if args.report else []
    return bench.main(argv)


def _run_demo(args: argparse.Namespace) -> int:
    if args.jaus is not None and args.processes:
        raise ConfigError("--jaus runs with the in-process demo, not --processes")
    if not args.processes:
        from ups.examples.robots import run_demo

        if args.jaus is not None:
            return run_until_signal(run_demo(args.duration, jaus=args.jaus))
        return run_until_signal(run_demo(args.duration or 3.0))
    if args.can is None:
        raise ConfigError(
            "--processes needs a bus that processes share: --can socketcan:vcan0, or "
            "udp_multicast inside scripts/netns-run (a virtual bus lives in one process)"
        )
    if args.can.startswith("virtual"):
        raise ConfigError("a virtual bus lives in one process: give --can socketcan:vcan0")
    if args.listen.endswith(":0"):
        raise ConfigError("--listen needs a port the parts can be told (not 0)")
    from ups.examples.fleet import run_fleet

    return run_until_signal(run_fleet(args.can, args.listen, args.duration))
