"""``ups c-node``: the C node library (c/, libups) run as a node on any python-can bus, to try it
without hardware and for the tests; ``ups uid`` and ``ups catalog --c-header``: channels as C
constants. Arguments here (cheap to build), the work in ``run`` functions."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from ups._channel import Channel
from ups._cliargs import (
    add_can,
    channel_arg,
    nonnegative_float,
    positive_float,
    positive_int,
    run_until_signal,
    say,
)

EXIT_FAILED = 1  #: the join or a channel's binding ended with an error
BOUND = 2  #: a channel's state once its etag is granted (libups's UPS_CHANNEL_BOUND)


def _pub_arg(text: str) -> tuple[Channel, bytes]:
    channel, sep, data = text.rpartition("=")
    if not sep or not channel:
        raise argparse.ArgumentTypeError(f"expected CHANNEL=HEX, not {text!r}")
    try:
        return channel_arg(channel), bytes.fromhex(data)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"bad hex data in {text!r}") from exc


def _node_id_arg(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a 64-bit number, not {text!r}") from None
    if not 0 <= value < 1 << 64:
        raise argparse.ArgumentTypeError(f"a node id has 64 bits: {text!r}")
    return value


def add_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    cmd = command("c-node", help="run the C node library (c/, libups) on a CAN bus")
    add_can(cmd)
    cmd.add_argument(
        "--node-id", type=_node_id_arg, default=None,
        help="the node's 64-bit id (default: one derived from this machine, as ups pub does)",
    )  # fmt: skip
    cmd.add_argument(
        "--pub", type=_pub_arg, action="append", default=[], metavar="CHANNEL=HEX",
        help="publish this payload on this channel (repeatable)",
    )  # fmt: skip
    cmd.add_argument(
        "--rate", type=positive_float, default=10.0, help="events per second per --pub (10)"
    )
    cmd.add_argument("--count", type=positive_int, default=1, help="events per --pub (1)")
    cmd.add_argument(
        "--sub", type=channel_arg, action="append", default=[], metavar="CHANNEL",
        help="print the events of this channel (repeatable)",
    )  # fmt: skip
    cmd.add_argument("--json", action="store_true", help="one JSON object per event, as ups sub")
    cmd.add_argument(
        "--duration", type=nonnegative_float, default=None,
        help="run this many seconds (default: until the --pub events are sent, or, with --sub, "
        "until interrupted)",
    )  # fmt: skip
    cmd.add_argument(
        "--build", choices=("full", "min", "asan"), default="full",
        help="the library's configuration: full (transfers, CAN FD), min (8 channels, 8 bytes) "
        "or asan (transfers and CAN FD with small tables, AddressSanitizer and "
        "UndefinedBehaviorSanitizer: run with LD_PRELOAD=$(cc -print-file-name=libasan.so))",
    )  # fmt: skip
    cmd.add_argument(
        "--target", choices=("host", "m0"), default="host",
        help="host: the library compiled for this machine; m0: the Cortex-M0+ image a board "
        "flashes (make -C c size's), run in an emulator (needs the emu extra: unicorn), "
        "--build full or min",
    )  # fmt: skip
    cmd.set_defaults(run=_run_c_node)

    cmd = command("uid", help="print channel UIDs as C constants")
    cmd.add_argument("names", nargs="+", metavar="NAME", help="channel names (or 0x UIDs)")
    cmd.set_defaults(run=_run_uid)

    cmd = command("catalog", help="write a catalog's channels as a C header (for libups)")
    cmd.add_argument(
        "--c-header", required=True, metavar="CATALOG",
        help="the catalog (TOML) whose channels' UIDs and payload layouts to write",
    )  # fmt: skip
    cmd.add_argument("-o", "--output", default=None, help="the header file (default: stdout)")
    cmd.set_defaults(run=_run_catalog)


def _run_uid(args: argparse.Namespace) -> int:
    from ups._cheader import c_define

    for name in args.names:
        print(c_define(channel_arg(name)))
    return 0


def _run_catalog(args: argparse.Namespace) -> int:
    from ups._catalog import Catalog
    from ups._cheader import c_header

    text = c_header(Catalog.load(args.c_header), args.c_header)
    if args.output is None:
        sys.stdout.write(text)
    else:
        with open(args.output, "w") as out:
            out.write(text)
    return 0


def _run_c_node(args: argparse.Namespace) -> int:
    import asyncio
    import json
    import time

    from ups._canlink import open_bus, parse_bus_spec
    from ups._cnode import ERRORS, CNode, CNodeRunner, Event, now_ms

    fd = parse_bus_spec(args.can).get("fd") is True
    node_id = args.node_id
    if node_id is None:
        from ups._nodeid import claim_node_id

        node_id, args.id_lock = claim_node_id("ups-c-node")
    if args.target == "m0":
        from ups._armnode import ArmNode

        if args.build == "asan":
            print("ups c-node: --target m0 runs --build full or min (no sanitizer on the board)",
                  file=sys.stderr)  # fmt: skip
            return 2
        node: CNode = ArmNode(node_id, fd=fd, config="full" if args.build == "full" else "minimal")
    else:
        node = CNode(node_id, fd=fd, variant=args.build)
    now = now_ms()
    subs = {node.subscribe(ch.uid, now): ch for ch in args.sub}
    pubs = [(node.advertise(ch.uid, len(data), now), ch, data) for ch, data in args.pub]
    sent = dict.fromkeys(range(len(pubs)), 0)

    received = 0

    def on_event(_: CNode, event: Event, timestamp: float) -> None:
        nonlocal received
        channel = subs.get(event.channel)
        if channel is None:
            return
        received += 1
        if args.json:
            line = json.dumps(
                {"uid": f"0x{channel.uid:016x}", "channel": channel.name,
                 "data": event.data.hex(), "timestamp": timestamp,
                 "priority": event.priority, "source": f"0x{event.txnode:02x}"}
            )  # fmt: skip
        else:
            line = (f"{channel}  {event.data.hex() or '-'}  prio={event.priority}  "
                    f"from=0x{event.txnode:02x}")  # fmt: skip
        print(line, flush=True)

    channels = [*subs.items(), *((c, ch) for c, ch, _ in pubs)]

    def failed(state: dict[int, int]) -> str | None:
        if node.join_state < 0:
            return f"the join failed: {ERRORS[node.join_state]}"
        for channel, ch in channels:
            if state[channel] < 0:
                return f"{ch}: {ERRORS[state[channel]]}"
        return None

    async def run() -> int:
        bus = open_bus(args.can)
        runner = CNodeRunner(bus, [node], on_event)
        runner.start_all()
        start = time.monotonic()
        announced = False
        bound: set[int] = set()  # the channels whose binding was said
        first: float | None = None
        try:
            while True:
                runner.step()
                state = {channel: node.channel_state(channel) for channel, _ in channels}
                if (why := failed(state)) is not None:
                    print(f"ups c-node: {why}", file=sys.stderr)
                    return EXIT_FAILED
                if not announced and node.txnode is not None:
                    announced = True
                    say(args, f"node {node_id:016x} joined as TxNode 0x{node.txnode:02x}")
                for channel, ch in channels:
                    if channel not in bound and state[channel] == BOUND:
                        bound.add(channel)
                        etag = node.channel_etag(channel)
                        use = "subscribed" if channel in subs else "publishing"
                        say(args, f"{use}: {ch} is etag 0x{etag:04x}")
                clock = time.monotonic()
                for k, (channel, _, data) in enumerate(pubs):
                    if sent[k] >= args.count or state[channel] != BOUND:
                        continue
                    first = clock if first is None else first
                    if clock >= first + sent[k] / args.rate and node.publish(channel, data) == 0:
                        sent[k] += 1
                done = all(n >= args.count for n in sent.values())
                if args.duration is not None:
                    if clock - start >= args.duration:
                        break
                elif pubs and done and not subs:
                    runner.step()  # the last frames out
                    break
                await asyncio.sleep(0.001)
        except asyncio.CancelledError:  # SIGTERM or SIGINT: a normal way to stop
            pass
        finally:
            bus.shutdown()
            for k, (_, ch, _) in enumerate(pubs):  # what was done, however the run ended
                short = f" of {args.count}" if sent[k] < args.count else ""
                say(args, f"published {sent[k]}{short} events on {ch}")
            if subs:
                say(args, f"received {received} events")
        return 0

    return run_until_signal(run())
