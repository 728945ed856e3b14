"""``ups record FILE``: the events of a network in a python-can log file (``.asc``, ``.blf``,
``.log``), with the bindings needed to read it back in ``FILE.ups.json``.

On CAN the file is the bus as it was: every UPS frame, management included (its Bind, PUB_AT
and SUB_AT frames say which channel each etag carried, its Assign frames which node each
TxNode was). What was bound before the recording began comes from the CAN-ECB's database when
it is on this host, and from the recorder's own subscription when channels are named: the
sidecar holds, for each etag in the file, the channel it carried when first recorded.

On TCP/IP there are no frames: each event becomes one (the CAN FD frame of its payload), its
channel a stand-in etag and its publisher a stand-in TxNode, and a Bind (Assign) frame written
before an etag's (TxNode's) first event says which. Events above 64 bytes do not fit a frame of
these formats: they are counted and reported, not written.

Frames that are not UPS (11-bit ids, error frames) are not written; they are counted.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

from .._channel import Channel
from .._cliargs import (
    add_catalog,
    add_network,
    add_tls,
    channel_arg,
    positive_float,
    positive_int,
    run_until_signal,
    say,
)
from .._errors import ConfigError, UpsError
from ._net import network_of

if TYPE_CHECKING:
    import asyncio

    import can

    from .._bindings import Bindings
    from ._net import IpNetwork


HELP = "record a network's events to a python-can log file (.asc, .blf, .log)"
FORMATS = (".asc", ".blf", ".log")
QUEUE = 65536  #: TCP/IP: events held while the file is written; beyond, counted as lost
FOLLOW_EVERY = 1.0  #: TCP/IP: seconds between looks at the TCP-ECB for new channels


def add_arguments(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument("file", metavar="FILE", help="the log file: .asc, .blf or .log (candump)")
    cmd.add_argument(
        "channels", nargs="*", type=channel_arg, metavar="CHANNEL",
        help="record only these (name or 0xUID; default: every channel)",
    )  # fmt: skip
    add_network(cmd, "record a CAN bus", "record an IP network")
    cmd.add_argument("--duration", type=positive_float, default=None, help="stop after S seconds")
    cmd.add_argument("--count", type=positive_int, default=None, help="stop after N events")
    cmd.add_argument("--db", default=None, help="CAN: the CAN-ECB's database (default: the bus's)")
    add_catalog(cmd)
    cmd.add_argument("--timeout", type=positive_float, default=5.0, help="seconds to wait")
    add_tls(cmd, node=True)


def check_format(path: str) -> str:
    from pathlib import Path

    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ConfigError(f"{path}: the log format is chosen by the suffix: {' '.join(FORMATS)}")
    return suffix


def run(args: argparse.Namespace) -> int:
    from .._bindings import Bindings
    from .._catalog import load_catalog

    check_format(args.file)
    can_bus, net = network_of(args)
    catalog = load_catalog(args.catalog)
    bindings = Bindings(network=net.label if net is not None else "can")
    if can_bus is not None:
        bindings.load_bus_db(can_bus, args.db)
    bindings.names.update({s.uid: s.name for s in catalog if s.name})
    bindings.names.update({c.uid: c.name for c in args.channels if c.name})
    recorder = _Recorder(args.file, {c.uid for c in args.channels}, bindings, args.count)
    try:
        if can_bus is not None:
            code = run_until_signal(_record_can(args, can_bus, recorder))
        else:
            assert net is not None
            code = run_until_signal(_record_ip(args, net, recorder))
    finally:
        recorder.close()
        if recorder.started:  # also when it stopped on an error: what it kept, and where
            print(recorder.summary(), file=sys.stderr)
    return code


class _Recorder:
    """The writer, what it has written and what it could not."""

    def __init__(self, path: str, only: set[int], bindings: Bindings, count: int | None) -> None:
        import threading
        from pathlib import Path

        import can

        from .._bindings import sidecar_of

        self.path = path
        self.sidecar = sidecar_of(path)
        name = Path(path).name  # written aside, and moved over FILE once recording began:
        self._part = Path(path).with_name(f".{name}.part{Path(path).suffix}")  # a failed
        self.started = False  # start leaves an earlier FILE as it was
        self.only = only
        self.bindings = bindings
        self.first_use: dict[int, int | None] = {}  #: etag -> its channel when first written
        self.first_node: dict[int, int | None] = {}  #: TxNode -> its node when first written
        self.events = self.management = 0
        self.count = count
        self.full = threading.Event()  #: set once ``count`` events are written, or on error
        self.error: OSError | None = None  #: writing failed (a full disk ...): recording stops
        self.skipped: dict[str, int] = {}
        self._writer: can.Listener = can.Logger(str(self._part))
        self._msg = can.Message

    def skip(self, why: str) -> None:
        self.skipped[why] = self.skipped.get(why, 0) + 1

    def frame(self, msg: can.Message) -> None:
        """A frame heard on the bus: learn from it, write it (or count why not). A write that
        fails stops the recording (``error``)."""
        try:
            self._frame(msg)
        except OSError as exc:
            self.error = exc
            self.full.set()

    def _frame(self, msg: can.Message) -> None:
        from .._bindings import Event, Fragment

        if msg.is_error_frame or not msg.is_extended_id or msg.is_remote_frame:
            self.skip("not UPS frames (11-bit, error or remote)")
            return
        item = self.bindings.read(
            msg.arbitration_id, bytes(msg.data), fd=msg.is_fd, now=msg.timestamp
        )
        if item is None:
            self.skip("malformed management frames")
            return
        if isinstance(item, Fragment):  # a frame of a larger event: kept, counted with it
            if self.full.is_set() or (self.only and item.uid not in self.only):
                return
        elif isinstance(item, Event):
            if self.only and item.uid not in self.only:
                if item.uid is None:
                    self.skip("events on etags not bound to a known channel")
                return  # another channel's: not asked for
            if self.full.is_set():
                return
            self.used(item.etag, item.txnode)
            if self.events == self.count:
                self.full.set()
        else:
            self.management += 1
        self._writer.on_message_received(msg)

    def used(self, etag: int, txnode: int) -> None:
        """One more event, on ``etag`` from ``txnode``: the sidecar keeps what the first one
        of each stood for (later bindings are in the file itself, where they happen)."""
        self.events += 1
        self.first_use.setdefault(etag, self.bindings.etags.get(etag))
        self.first_node.setdefault(txnode, self.bindings.txnodes.get(txnode))

    def write(self, timestamp: float, can_id: int, data: bytes, fd: bool = False) -> None:
        self._writer.on_message_received(
            self._msg(
                timestamp=timestamp, arbitration_id=can_id, is_extended_id=True,
                is_fd=fd or len(data) > 8, bitrate_switch=fd, data=data,
            )
        )  # fmt: skip

    def close(self) -> None:
        """Close the file; once recording began, move it over FILE and write its sidecar,
        else remove it (an earlier FILE stays as it was)."""
        self._writer.stop()
        if not self.started:
            self._part.unlink(missing_ok=True)
            return
        self._part.replace(self.path)
        bindings = self.bindings
        saved = type(bindings)(
            {e: u for e, u in self.first_use.items() if u is not None},
            {t: n for t, n in self.first_node.items() if n is not None},
            {u: n for u, n in bindings.names.items() if u in self.first_use.values()},
            bindings.network,
        )
        saved.save(self.sidecar)

    def summary(self) -> str:
        channels = len({u for u in self.first_use.values() if u is not None})
        text = (
            f"ups record: {self.events} events on {channels} channels and "
            f"{self.management} management frames in {self.path} (bindings: {self.sidecar})"
        )
        for why, count in self.skipped.items():
            text += f"; not recorded: {count} {why}"
        return text


async def _record_can(args: argparse.Namespace, bus: str, rec: _Recorder) -> int:
    import asyncio
    import threading

    import can

    from .._canlink import open_bus

    listener = open_bus(bus)
    try:
        stop = threading.Event()
        loop = asyncio.get_running_loop()
        deadline = None if args.duration is None else time.monotonic() + args.duration

        def pump() -> None:  # python-can's recv blocks: a thread, stopped by the event
            while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                if rec.full.is_set():
                    break
                msg = listener.recv(0.1)
                if msg is not None:
                    loop.call_soon_threadsafe(rec.frame, msg)

        reader = asyncio.create_task(asyncio.to_thread(pump))
        try:
            if rec.only:  # join and subscribe: the CAN-ECB binds (or re-announces) their etags
                await _subscribe_can(bus, args, rec, reader)
            else:
                rec.started = True
                say(args, f"recording {bus} to {args.file}")
                await reader
        finally:
            stop.set()
            await asyncio.gather(reader, return_exceptions=True)
        reader.result()  # the bus failed: say so
    except can.CanError as exc:
        raise UpsError(f"the bus failed: {exc}") from None
    finally:
        listener.shutdown()
    if rec.error is not None:
        raise rec.error
    return 0


async def _subscribe_can(
    bus: str, args: argparse.Namespace, rec: _Recorder, reader: asyncio.Task[Any]
) -> None:
    from .._node import Node

    channels = [Channel(uid, rec.bindings.names.get(uid)) for uid in sorted(rec.only)]
    async with Node(can=bus, name="ups-record", join_timeout=args.timeout) as node:
        await node.subscribe(*channels)
        rec.started = True
        say(args, f"recording {', '.join(map(str, channels))} to {args.file}")
        await reader


class _StandIns:
    """Stand-in numbers (etags or TxNodes) for keys (UIDs or node ids), at most ``size`` at a
    time: the least recently used is given to a new key, and the caller writes the new
    binding before the frame that uses it."""

    def __init__(self, first: int, size: int) -> None:
        self._first, self._size = first, size
        self._numbers: OrderedDict[int, int] = OrderedDict()

    def get(self, key: int) -> tuple[int, bool]:
        """``(number, new)``: ``new`` when the binding must be written first."""
        number = self._numbers.get(key)
        if number is not None:
            self._numbers.move_to_end(key)
            return number, False
        if len(self._numbers) < self._size:
            number = self._first + len(self._numbers)
        else:
            _, number = self._numbers.popitem(last=False)
        self._numbers[key] = number
        return number, True


async def _record_ip(args: argparse.Namespace, net: IpNetwork, rec: _Recorder) -> int:
    import asyncio

    from .. import _canproto as p

    loop = asyncio.get_running_loop()
    from .. import _cantransfer as t

    small, large = t.class_etags(0), t.class_etags(4)
    etags = _StandIns(small.start, len(small))  # events of 8 bytes or fewer: one frame
    large_etags = _StandIns(large.start, len(large))  # larger ones: transfers of FD frames
    tids: dict[int, int] = {}
    txnodes = _StandIns(0, p.TXNODE_COUNT)
    names = rec.bindings.names
    async with net.node("ups-record") as node:
        subscribed = set(rec.only)
        if rec.only:
            await node.subscribe(*[Channel(u, names.get(u)) for u in rec.only], maxlen=QUEUE)

        async def follow() -> None:  # every channel: subscribe to those the network lists
            while True:
                status = await net.status()
                for c in status.get("channels", ()):
                    uid = int(c["uid"], 16)
                    if c.get("name"):
                        names.setdefault(uid, c["name"])
                    if uid not in subscribed:
                        subscribed.add(uid)
                        await node.subscribe(Channel(uid, names.get(uid)), maxlen=QUEUE)
                await asyncio.sleep(FOLLOW_EVERY)

        follower = None if rec.only else asyncio.create_task(follow())
        rec.started = True
        say(args, f"recording {net} to {args.file}")
        deadline = None if args.duration is None else loop.time() + args.duration
        try:
            while deadline is None or loop.time() < deadline:
                if follower is not None and follower.done():
                    follower.result()  # the TCP-ECB went away: say so, do not record nothing
                left = 1.0 if deadline is None else min(1.0, max(0.0, deadline - loop.time()))
                try:
                    msg = await node.get_msg(timeout=left)
                except TimeoutError:
                    continue
                if len(msg.data) > t.MAX_EVENT:
                    rec.skip(f"events above {t.MAX_EVENT} bytes")
                    continue
                pool = etags if len(msg.data) <= p.CLASSIC_MAX_DATA else large_etags
                etag, new = pool.get(msg.uid)
                if new:
                    rec.bindings.etags[etag] = msg.uid
                    rec.write(msg.timestamp, *p.encode(p.Bind(etag, msg.uid)))
                    rec.management += 1
                source = msg.source if msg.source is not None else node.node_id
                txnode, new = txnodes.get(source)
                if new:
                    rec.bindings.txnodes[txnode] = source
                    rec.write(msg.timestamp, *p.encode(p.Assign(txnode, source)))
                    rec.management += 1
                priority = max(msg.priority, p.FIRST_EVENT_PRIORITY)
                can_id = p.make_id(priority, txnode, etag)
                if pool is etags:
                    rec.write(msg.timestamp, can_id, msg.data)
                else:
                    tid = tids[etag] = (tids.get(etag, -1) + 1) & t.TID_MASK
                    for frame in t.segment(msg.data, tid, 64):
                        rec.write(msg.timestamp, can_id, frame, fd=True)
                rec.used(etag, txnode)
                if rec.events == rec.count:
                    break
        finally:
            if follower is not None:
                follower.cancel()
                await asyncio.gather(follower, return_exceptions=True)
        lost = node.stats().get("dropped", 0) + node.stats().get("lost", 0)
        if lost:
            rec.skipped["events lost on the way (a full queue or sequence gaps)"] = lost
    return 0
