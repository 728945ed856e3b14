"""``ups pub`` and ``ups sub``: publishing and subscribing from a shell. Their arguments here
(cheap to build), their work in ``run`` functions that import what they need."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

from ups._cliargs import (
    add_catalog,
    add_node_options,
    channel_arg,
    channel_or_pattern_arg,
    hex_arg,
    nonnegative_float,
    open_node,
    positive_float,
    positive_int,
    priority_arg,
    run_until_signal,
    say,
)
from ups._errors import ConfigError

if TYPE_CHECKING:
    from ups._catalog import Catalog
    from ups._channel import Channel
    from ups._message import Message
    from ups._subscription import Subscription

EXIT_TIMEOUT = 1  #: ups sub saw fewer events than --count before --timeout
EXIT_LOST = 1  #: ups sub lost events, ups pub could not deliver some


def add_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    cmd = command("pub", help="publish events on a channel")
    cmd.add_argument("channel", type=channel_arg, help="channel name, or UID as 0x + hex")
    cmd.add_argument(
        "data", help="payload as hex digits ('' for none), or field=value,... that the "
        "catalog's layout of the channel encodes (e.g. left=1.5,right=1.5)",
    )  # fmt: skip
    add_catalog(cmd)
    add_node_options(cmd)
    cmd.add_argument("--count", type=positive_int, default=1, help="events to publish")
    cmd.add_argument(
        "--rate",
        type=nonnegative_float,
        default=10.0,
        help="events per second (0: as fast as possible)",
    )
    cmd.add_argument(
        "--priority", type=priority_arg, default=None,
        help="0 (highest)..255 (default: the catalog's, else 0x80)",
    )  # fmt: skip
    cmd.add_argument(
        "--wait", action="store_true",
        help="wait for room at slow subscribers instead of dropping (TCP/IP backpressure)",
    )  # fmt: skip
    cmd.set_defaults(run=_run_pub)

    cmd = command("sub", help="print the events of channels, or of every channel a pattern "
                  "matches")  # fmt: skip
    cmd.add_argument(
        "channels", nargs="+", type=channel_or_pattern_arg, metavar="CHANNEL",
        help="a name, 0x + hex for a UID, or a pattern: a name with *, ? or [ (robot/*; '*' "
        "crosses '/'), for every channel whose name matches, now and later: on TCP/IP the "
        "TCP-ECB's names, on Zenoh names in keys (from a channel's first event), on CAN the "
        "catalog's (--catalog)",
    )  # fmt: skip
    add_catalog(cmd, "names and payload layouts: events printed as decoded values")
    add_node_options(cmd)
    cmd.add_argument("--count", type=positive_int, default=None, help="exit 0 after N events")
    cmd.add_argument(
        "--timeout", type=positive_float, default=None, help="exit 1 if this many s pass"
    )
    cmd.add_argument("--json", action="store_true", help="one JSON object per line")
    cmd.add_argument(
        "--queue", type=positive_int, default=1024,
        help="events held while the output is slow (default 1024); beyond, the oldest are lost",
    )  # fmt: skip
    cmd.set_defaults(run=_run_sub)


def _run_pub(args: argparse.Namespace) -> int:
    import asyncio

    from ups._catalog import load_catalog

    catalog = load_catalog(args.catalog) if "=" in args.data else None
    args.data = catalog.payload(args.channel, args.data) if catalog else hex_arg(args.data)

    if args.priority is None:  # the catalog's, when it gives one
        spec = (catalog or load_catalog(args.catalog)).get(args.channel.uid)
        args.priority = None if spec is None else spec.priority

    async def run() -> int:
        async with open_node(args) as node:
            if args.priority is not None:
                node.set_priority(args.channel, args.priority)
            loop = asyncio.get_running_loop()
            start = loop.time()
            for i in range(args.count):
                if args.rate <= 0:
                    await asyncio.sleep(0)  # flat out, but let the writes drain
                elif i:
                    await asyncio.sleep(max(0.0, start + i / args.rate - loop.time()))
                await node.publish(args.channel, args.data, wait=args.wait)
        stats = node.stats()  # after closing: what could not be delivered is counted by now
        if stats.get("tx_failed"):
            print(f"ups pub: {stats['tx_failed']} frames could not be sent", file=sys.stderr)
            return 1
        if stats.get("peer_dropped"):
            print(f"ups pub: {stats['peer_dropped']} events were dropped", file=sys.stderr)
            return 1
        return 0

    return run_until_signal(run())


def _run_sub(args: argparse.Namespace) -> int:
    import asyncio

    from ups._catalog import load_catalog

    catalog = load_catalog(args.catalog)
    node = open_node(args)
    patterns = [c for c in args.channels if isinstance(c, str)]
    if patterns and args.on_can and catalog.path is None:  # said before joining the bus
        raise ConfigError(f"on CAN, channel names come only from a channel catalog: "
                          f"subscribing to {patterns[0]} needs one (--catalog FILE or "
                          "$UPS_CATALOG)")  # fmt: skip

    _unknown_to_the_catalog(args, catalog)

    async def run() -> int:
        got = 0
        code = 0
        async with node:
            sub = await node.subscribe(*args.channels, maxlen=args.queue)
            say(args, f"subscribed to {_subscribed(args.channels, sub, args.on_can)}")
            loop = asyncio.get_running_loop()
            deadline = None if args.timeout is None else loop.time() + args.timeout
            try:
                while args.count is None or got < args.count:
                    left = None if deadline is None else max(0.0, deadline - loop.time())
                    try:
                        msg = await sub.get_msg(timeout=left)
                    except TimeoutError:
                        print(f"ups sub: timeout after {got} events", file=sys.stderr)
                        code = EXIT_TIMEOUT
                        break
                    got += 1
                    print(_event_line(msg, args.json, args.on_can, catalog), flush=True)
            except asyncio.CancelledError:  # SIGTERM or SIGINT: a normal way to stop
                print(f"ups sub: stopped after {got} events", file=sys.stderr)
            stats = node.stats()
            dropped, skipped = sub.dropped, stats.get("lost", 0) + stats.get("large_lost", 0)
        if dropped or skipped:  # every loss is reported, however the run ended
            print(
                f"ups sub: lost {dropped + skipped} events: {dropped} dropped from its full "
                f"queue (--queue {args.queue}), {skipped} missing on the way (sequence gaps, "
                "broken CAN transfers)",
                file=sys.stderr,
            )
            return code or EXIT_LOST
        return code

    return run_until_signal(run())


def _unknown_to_the_catalog(args: argparse.Namespace, catalog: Catalog) -> None:
    """Say which channel names the catalog given does not have (a typo waits for ever)."""
    import difflib

    if catalog.path is None:
        return
    names = [spec.name for spec in catalog if spec.name]
    for chan in args.channels:
        if isinstance(chan, str) or chan.name is None or catalog.get(chan.uid) is not None:
            continue
        close = difflib.get_close_matches(chan.name, names, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        say(args, f"{chan.name} is not in the catalog {catalog.path}{hint}")


def _subscribed(asked: list[Channel | str], sub: Subscription, on_can: bool) -> str:
    """What ``ups sub`` says it subscribed to: the channels, and for patterns what they match
    (on CAN the catalog's channels, all known at once; elsewhere more come as they are named)."""
    said = [str(c) for c in asked if not isinstance(c, str)]
    if sub.patterns:
        matched = [str(c) for c in sub.channels if all(c != a for a in asked)]
        now = ", ".join(matched[:10]) + (f" and {len(matched) - 10} more" if matched[10:] else "")
        later = "" if on_can else "; more join as they are named"
        said.append(f"{', '.join(sub.patterns)} ({now or 'no channel yet'}{later})")
    return ", ".join(said)


def _event_line(msg: Message, as_json: bool, on_can: bool, catalog: Catalog) -> str:
    """One event as ``ups sub`` prints it: its channel (named by the catalog when the event
    came by UID), its data (decoded by the catalog's layout of the channel, if any), priority
    and source. The source is hex: a TxNode (2 digits) on CAN, a node id (16 digits) on TCP/IP
    and Zenoh, null for the node's own events."""
    digits = 2 if on_can else 16
    source = None if msg.source is None else f"0x{msg.source:0{digits}x}"
    uid = msg.channel.uid
    name = msg.channel.name or catalog.channel(uid).name
    if as_json:
        import json  # cached after the first event: a dict lookup

        values = catalog.decode(uid, msg.data)
        return json.dumps(
            {
                "uid": f"0x{uid:016x}",
                "channel": name,
                "data": msg.data.hex(),
                "values": None
                if values is None
                else {k: v.hex() if isinstance(v, bytes) else v for k, v in values.items()},
                "timestamp": msg.timestamp,
                "priority": msg.priority,
                "source": source,
            }
        )
    value = catalog.format(uid, msg.data)
    return f"{name or msg.channel}  {value}  prio={msg.priority}  from={source or '-'}"
