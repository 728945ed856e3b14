"""``ups ethercat --ifname IF --map FILE (--can BUS | --broker HOST:PORT | --zenoh ENDPOINT)``:
the EtherCAT master of a segment on a UPS node, until a signal."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys

from ups._cliargs import node_for, say

from ._bridge import EthercatNode
from ._cycle import Segment
from ._map import EthercatMap
from ._master import EthercatError

SWITCH_INTERVAL = 0.0002  #: s: see serve


async def serve(args: argparse.Namespace, emap: EthercatMap) -> int:
    cycle = args.cycle / 1000 if args.cycle else None
    # the cycle's thread waits for the interpreter lock at most this long when it wakes while
    # the event loop runs Python (Python's default, 5 ms, is longer than a cycle)
    sys.setswitchinterval(SWITCH_INTERVAL)
    segment = Segment(args.ifname, emap, cycle)
    # the identities are checked before UPS sees anything; a signal meanwhile waits for the
    # start to end (a thread cannot be cancelled), then stops the segment
    starting = asyncio.ensure_future(asyncio.to_thread(segment.start))
    try:
        await asyncio.shield(starting)
    except asyncio.CancelledError:
        with contextlib.suppress(Exception):
            await starting
            await asyncio.to_thread(segment.stop)
        raise
    try:
        _, node = node_for(args, "ups-ethercat")
        async with node:
            bridge = EthercatNode(node, segment)
            await bridge.start()
            face = node.face
            if hasattr(face, "extra_status"):  # TCP and Zenoh nodes answer `ups status`
                face.extra_status = bridge.status
            status = segment.status()
            address = getattr(face, "address", None)
            ask = f"; ups status {address[0]}:{address[1]}" if address else ""
            say(args, f"master of {status['slaves']} slave(s) on {args.ifname}, "
                f"{status['in_op']} in OP, cycle {status['cycle_ms']:g} ms{ask}")  # fmt: skip
            failed = asyncio.Event()
            loop = asyncio.get_running_loop()

            def on_failure() -> None:
                loop.call_soon_threadsafe(failed.set)

            segment.on_failure = on_failure
            if segment.failure is not None:  # (it stopped before it could say so)
                failed.set()
            try:
                await failed.wait()  # or a signal
                raise EthercatError(f"the EtherCAT cycle stopped: {segment.failure}")
            finally:
                await bridge.close()
    finally:
        await asyncio.to_thread(segment.stop)
    return 0
