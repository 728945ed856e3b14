"""What the ``ups`` commands share: their common options, argument types, the choice of
network, and running a command's coroutine until a signal."""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Coroutine
from typing import TYPE_CHECKING, Any

from ._channel import Channel, check_pattern, is_pattern, parse_channel
from ._errors import BrokerUnavailable, ConfigError, UpsError

if TYPE_CHECKING:
    from ._node import Node
    from ._tls import Tls


#: seconds a command waits for a CAN-ECB unless told (--join-timeout): on a bus, nothing
#: refuses a connection, and a CAN-ECB is known only by its answer
CAN_JOIN_TIMEOUT = 30.0
#: why a command that joins a bus as a node refuses a python-can virtual bus
VIRTUAL_ALONE = (
    "{bus} is a python-can virtual bus, which lives inside one process: this command would be "
    "alone on it, whatever another process opens under that name; across processes use "
    "--can udp_multicast:239.74.163.2,port=43114 inside scripts/netns-run, or SocketCAN "
    "(--can socketcan:vcan0)"
)


def warn_if_virtual(bus: str) -> None:
    """A daemon on a python-can virtual bus is alone there: say so, once, at start."""
    if bus.split(":", 1)[0].strip() == "virtual":
        import logging

        logging.getLogger("ups").warning(
            "%s is a python-can virtual bus, which lives inside this process: nodes in other "
            "processes cannot reach it (across processes: --can udp_multicast:239.74.163.2,"
            "port=43114 inside scripts/netns-run, or --can socketcan:vcan0)", bus,
        )  # fmt: skip


def add_can(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument(
        "--can",
        default=os.environ.get("UPS_CAN") or None,
        required=not os.environ.get("UPS_CAN"),
        metavar="INTERFACE:CHANNEL[,key=value...]",
        help="python-can bus, e.g. socketcan:vcan0 or udp_multicast:239.74.163.2,port=43114 "
        "(default: $UPS_CAN)",
    )


def add_node_options(cmd: argparse.ArgumentParser) -> None:
    network = cmd.add_mutually_exclusive_group()  # or $UPS_BROKER, $UPS_ZENOH, $UPS_CAN
    network.add_argument(
        "--can",
        metavar="INTERFACE:CHANNEL[,key=value...]",
        help="python-can bus, e.g. socketcan:vcan0 or udp_multicast:239.74.163.2,port=43114 "
        "(default: $UPS_CAN, when neither $UPS_BROKER nor $UPS_ZENOH is set)",
    )
    network.add_argument(
        "--broker", metavar="HOST:PORT",
        help="TCP/IP network served by the TCP-ECB at HOST:PORT (default: $UPS_BROKER)",
    )  # fmt: skip
    add_zenoh(network)
    cmd.add_argument(
        "--listen", metavar="HOST:PORT", default=None,
        help="TCP/IP: where publishers reach this node (default: towards the broker, any port)",
    )  # fmt: skip
    cmd.add_argument("--node-id", type=lambda t: int(t, 0), default=None, help="64-bit node id")
    cmd.add_argument(
        "--join-timeout", type=positive_float, default=None, metavar="S",
        help="wait up to S seconds for the broker (TCP-ECB, Zenoh router or CAN-ECB), also one "
        "not started yet (default: on TCP/IP and Zenoh one try, so nothing listening fails at "
        f"once; on CAN {CAN_JOIN_TIMEOUT:g} s, as a CAN-ECB is known only by its answer)",
    )  # fmt: skip
    add_zenoh_config(cmd)
    add_tls(cmd, node=True)


def add_zenoh(group: Any, required: bool = False) -> None:
    group.add_argument(
        "--zenoh", metavar="ENDPOINT", required=required,
        help="Zenoh network, through the router at ENDPOINT, e.g. tcp/127.0.0.1:7447 "
        "(default: $UPS_ZENOH)",
    )  # fmt: skip


def add_zenoh_config(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument(
        "--zenoh-config", metavar="FILE", default=None,
        help="Zenoh JSON5 config (TLS, user/password, access control, scouting); with it "
        "alone, the node joins Zenoh as the file says",
    )  # fmt: skip


def add_tls(cmd: argparse.ArgumentParser, node: bool = False) -> None:
    tls = cmd.add_argument_group("TLS (TCP/IP; all three, from 'ups certs')")
    tls.add_argument("--tls-ca", metavar="FILE", help="the fleet CA's certificate")
    tls.add_argument("--tls-cert", metavar="FILE", help="this participant's certificate")
    tls.add_argument("--tls-key", metavar="FILE", help="this participant's private key")
    if node:
        tls.add_argument(
            "--tls-broker", metavar="NAME", default="broker",
            help="the identity the TCP-ECB's certificate must show (default: broker)",
        )  # fmt: skip


def tls_of(args: argparse.Namespace) -> Tls | None:
    from ._tls import Tls

    broker = getattr(args, "tls_broker", "broker")  # the commands that join a TCP-ECB have it
    return Tls.from_files(args.tls_ca, args.tls_cert, args.tls_key, broker)


def channel_arg(text: str) -> Channel:
    """A channel: a name, or 0x + hex for a UID. A pattern is refused (never taken as the
    name of one channel): only ``ups sub`` takes patterns."""
    if is_pattern(text):
        raise argparse.ArgumentTypeError(
            f"{text} is a pattern (it holds *, ? or [), and this command takes channels; a "
            "channel whose name holds one is given by its UID, 0x..."
        )
    try:
        return parse_channel(text)
    except UpsError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def channel_or_pattern_arg(text: str) -> Channel | str:
    """A channel (as ``channel_arg``), or a pattern: a name holding ``*``, ``?`` or ``[``."""
    try:
        return check_pattern(text) if is_pattern(text) else parse_channel(text)
    except UpsError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def hex_arg(text: str) -> bytes:
    from ._catalog import hex_bytes

    return hex_bytes(text)


def positive_float(text: str) -> float:
    value = float(text)
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def nonnegative_float(text: str) -> float:
    value = float(text)
    if not 0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a finite number, 0 or more, got {text}")
    return value


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def priority_arg(text: str) -> int:
    value = int(text, 0)
    if not 0 <= value <= 255:
        raise argparse.ArgumentTypeError(f"priority must be 0..255, got {value}")
    return value


def run_until_signal(coro: Coroutine[Any, Any, int]) -> int:
    """Run ``coro`` (on uvloop when installed); SIGTERM and SIGINT cancel it, so every
    resource closes before exit. The exit code is then 0 after SIGTERM (a daemon asked to
    stop) and 130 after SIGINT (Ctrl-C, as a shell reports it), else what ``coro`` returns."""

    import asyncio
    import signal

    async def wrapper() -> int:
        task = asyncio.current_task()
        assert task is not None
        loop = asyncio.get_running_loop()
        caught: list[int] = []

        def stop(sig: int) -> None:
            caught.append(sig)
            task.cancel()

        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop, sig)
        try:
            code = await coro
        except asyncio.CancelledError:
            code = 0
        return 130 if signal.SIGINT in caught else code

    try:
        import uvloop  # the faster event loop, when installed (pip install ups-pubsub[fast])
    except ImportError:
        return asyncio.run(wrapper())
    return uvloop.run(wrapper())


def network_choice(args: argparse.Namespace) -> tuple[str, str]:
    """The network a command joins: ("can", BUS), ("broker", HOST:PORT) or ("zenoh",
    ENDPOINT), from the options, else the environment (UPS_BROKER, UPS_ZENOH, UPS_CAN)."""
    zenoh_config = getattr(args, "zenoh_config", None)
    given = [
        (kind, where)
        for kind, where in (
            ("can", args.can),
            ("broker", args.broker),
            ("zenoh", getattr(args, "zenoh", None)),
        )
        if where is not None
    ]
    if not given and zenoh_config is not None:
        given = [("zenoh", os.environ.get("UPS_ZENOH") or "")]
    for kind, variable in (("broker", "UPS_BROKER"), ("zenoh", "UPS_ZENOH"), ("can", "UPS_CAN")):
        if not given and os.environ.get(variable):
            given = [(kind, os.environ[variable])]
    if not given:
        raise ConfigError(
            "which network? give --can INTERFACE:CHANNEL, --broker HOST:PORT or --zenoh "
            "ENDPOINT (or set UPS_CAN, UPS_BROKER or UPS_ZENOH)"
        )
    kind, where = given[0]
    if zenoh_config is not None and kind != "zenoh":
        raise ConfigError("--zenoh-config is for Zenoh nodes (with --zenoh)")
    return kind, where


def open_node(args: argparse.Namespace) -> Node:
    """The node of a command that joins a network (``add_node_options``; not started). Unless
    ``--join-timeout`` says to wait, a TCP-ECB or Zenoh router that is not there fails at
    once; so does a virtual CAN bus, where this process would be alone."""
    from ._node import Node

    kind, where = network_choice(args)
    if args.listen is not None and kind != "broker":
        raise ConfigError("--listen is for TCP/IP nodes (with --broker)")
    tls = tls_of(args)
    if tls is not None and kind != "broker":
        raise ConfigError("--tls-* is for TCP/IP nodes; on Zenoh, TLS is in --zenoh-config")
    if kind == "can":
        from ._canlink import check_bus_spec

        if check_bus_spec(where)["interface"] == "virtual":
            raise ConfigError(VIRTUAL_ALONE.format(bus=where))
    args.on_can = kind == "can"  # what ``source`` is: a TxNode or a node id
    join_timeout = args.join_timeout
    if join_timeout is None:
        join_timeout = CAN_JOIN_TIMEOUT if kind == "can" else 0.0  # 0: one try
    catalog = None  # on CAN, where names come from for pattern subscriptions
    if kind == "can" and hasattr(args, "catalog"):
        catalog = args.catalog or os.environ.get("UPS_CATALOG") or None
    return Node(
        can=where if kind == "can" else None,
        broker=where if kind == "broker" else None,
        zenoh=where if kind == "zenoh" else None,
        listen=args.listen,
        node_id=args.node_id,
        name=f"ups-{args.command}",
        join_timeout=join_timeout,
        tls=tls,
        zenoh_config=getattr(args, "zenoh_config", None),
        catalog=catalog,
    )


def explained(args: argparse.Namespace, exc: UpsError) -> str:
    """The line a command prints for ``exc``: its text, and how to wait for a broker that is
    not up yet when the command did not wait (``--join-timeout``)."""
    text = str(exc)
    waits = getattr(args, "join_timeout", 0)
    if isinstance(exc, BrokerUnavailable) and waits is None and not getattr(args, "on_can", 1):
        text += "; or give --join-timeout S to wait up to S s for it"
    return text


def node_for(args: argparse.Namespace, name: str) -> tuple[str, Node]:
    """The node a bridge daemon (``ups jaus``, ``ups ros2``, ``ups ethercat``) joins with:
    on the network of :func:`network_choice`, with ``--node-id`` and ``--timeout`` to join;
    and that network's kind ("can", "broker" or "zenoh")."""
    from ._node import Node

    kind, where = network_choice(args)
    node = Node(
        can=where if kind == "can" else None,
        broker=where if kind == "broker" else None,
        zenoh=where if kind == "zenoh" else None,
        zenoh_config=getattr(args, "zenoh_config", None),
        node_id=args.node_id,
        name=name,
        join_timeout=args.timeout,
    )
    return kind, node


def add_network(cmd: argparse.ArgumentParser, can_help: str, ip_help: str) -> None:
    """``--can BUS | --broker HOST:PORT | --zenoh ENDPOINT`` (else the environment: see
    network_choice), and ``--zenoh-config``."""
    network = cmd.add_mutually_exclusive_group()
    network.add_argument(
        "--can", metavar="INTERFACE:CHANNEL[,key=value...]", help=f"{can_help} (default: $UPS_CAN)"
    )
    network.add_argument(
        "--broker", metavar="HOST:PORT", help=f"{ip_help}: ask its TCP-ECB (default: $UPS_BROKER)"
    )
    network.add_argument(
        "--zenoh", metavar="ENDPOINT",
        help=f"{ip_help} on Zenoh, through the router at ENDPOINT (default: $UPS_ZENOH)",
    )  # fmt: skip
    add_zenoh_config(cmd)


def add_catalog(cmd: argparse.ArgumentParser, what: str = "names and payload layouts") -> None:
    cmd.add_argument(
        "--catalog", metavar="FILE", default=None,
        help=f"TOML channel catalog: {what} (default: $UPS_CATALOG)",
    )  # fmt: skip


def say(args: argparse.Namespace, text: str) -> None:
    """One line of what a command is doing, on stderr (whatever the log level)."""
    import sys

    print(f"ups {args.command}: {text}", file=sys.stderr, flush=True)
