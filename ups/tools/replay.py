"""``ups replay FILE``: publish a recording's events again, on a live CAN bus or TCP/IP network.

Each event is published by its channel UID through the live network's own bindings (this
node joins and binds its channels like any other), so a bus whose etags were bound in another
order still carries every event on its own channel. Management frames of the recording are
never sent. Events keep their spacing in time (``--speed`` scales it) and their priority.

What cannot be replayed is counted and reported: events on etags the recording does not bind
to a channel, events too large for the target network.
"""

from __future__ import annotations

import argparse
import sys
import time

from .._channel import Channel
from .._cliargs import add_node_options, open_node, positive_float, run_until_signal
from .decode import Tally, bindings_for, read

HELP = "publish a recording's events again on a live network, by channel UID"
PROGRESS_EVERY = 1.0  #: seconds between progress lines on stderr


def add_arguments(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument("file", metavar="FILE", help="a recording (ups record) or a UPS bus's log")
    cmd.add_argument(
        "--bindings", metavar="FILE", default=None,
        help="the recording's bindings (default: FILE.ups.json when it exists)",
    )  # fmt: skip
    cmd.add_argument(
        "--speed", type=positive_float, default=1.0,
        help="time scale: 2 replays twice as fast (default 1: as recorded)",
    )  # fmt: skip
    add_node_options(cmd)


def run(args: argparse.Namespace) -> int:
    from .._bindings import Event

    bindings = bindings_for(args.file, args.bindings, None)
    total = Tally()
    for _ in read(args.file, bindings, total):  # a first pass: how much, and every channel
        pass
    bindings = bindings_for(args.file, args.bindings, None)  # the second pass learns anew
    names = bindings.names
    node = open_node(args)
    counts = {"sent": 0, "too large": 0}

    async def replay() -> int:
        import asyncio

        from .._errors import PayloadTooLarge

        async with node:
            loop = asyncio.get_running_loop()
            start: float | None = None
            first = 0.0
            priorities: dict[int, int] = {}
            announced = loop.time()
            tally = Tally()
            for timestamp, item in read(args.file, bindings, tally):
                if not isinstance(item, Event) or item.uid is None:
                    continue
                channel = Channel(item.uid, names.get(item.uid))
                if item.uid not in priorities:
                    await node.advertise(channel)  # bind before the clock starts to matter
                if priorities.get(item.uid) != item.priority:
                    priorities[item.uid] = item.priority
                    node.set_priority(channel, item.priority)
                if start is None:
                    start, first = loop.time(), timestamp
                due = start + (timestamp - first) / args.speed
                if due > loop.time():
                    await asyncio.sleep(due - loop.time())
                try:
                    await node.publish(channel, item.data)
                    counts["sent"] += 1
                except PayloadTooLarge:
                    counts["too large"] += 1
                if loop.time() - announced >= PROGRESS_EVERY:
                    announced = loop.time()
                    done = tally.events
                    print(
                        f"ups replay: {done}/{total.events} events "
                        f"({100 * done // max(1, total.events)} %)",
                        file=sys.stderr,
                        flush=True,
                    )
        return 0

    began = time.monotonic()
    code = run_until_signal(replay())
    stats = node.stats()
    failed = stats.get("tx_failed", 0) + stats.get("peer_dropped", 0)
    print(
        f"ups replay: published {counts['sent']} of {total.events} events in "
        f"{time.monotonic() - began:.1f} s; not replayed: {total.unbound} on etags bound to "
        f"no known channel, {counts['too large']} too large for this network, "
        f"{total.management} management frames (never replayed); {failed} not delivered",
        file=sys.stderr,
    )
    unfinished = counts["sent"] + counts["too large"] < total.events - total.unbound
    if failed or total.unbound or counts["too large"] or unfinished:
        return 1  # not all of it replayed: stopped early, or some of it could not be
    return code
