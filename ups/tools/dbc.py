"""``ups dbc -o FILE.dbc``: a DBC file (written by cantools) that labels a UPS bus's event
frames, so SavvyCAN, cantools and vendor tools show channels and decoded signals.

A DBC names a frame by its whole identifier, and a UPS identifier holds the priority, the
publisher's TxNode and the channel's etag, all three chosen on the bus at run time. So a DBC
is true for one bus as it is bound now: one message per (priority, TxNode, etag) in use, taken
from the live bus (``--can BUS``: its CAN-ECB's database and a moment of listening) or from a
recording (``--recording FILE``). The catalog (``--catalog``) gives names and the signals of
each channel's layout; a channel without one gets a single ``raw`` signal when it fits 64 bits.
Run it again after the CAN-ECB gives out etags or TxNodes anew (a lost database, a lease).

A channel whose events are larger than one frame is sent as transfers of several frames, on
etags of their own (from 0x3000): a DBC message is one frame, so none describes them. Such
channels are left out, and said so by name.
"""

from __future__ import annotations

import argparse
import re
import sys
from typing import TYPE_CHECKING, Any

from .._cliargs import add_catalog, positive_float
from .._errors import ConfigError

if TYPE_CHECKING:
    from .._bindings import Bindings
    from .._catalog import Catalog, ChannelSpec

HELP = "write a DBC that labels a UPS bus's frames (for cantools, SavvyCAN ...)"
Stream = tuple[int, int, int]  #: (priority, TxNode, etag) of frames in use
Streams = dict[Stream, tuple[int | None, int]]  #: -> (channel UID then, longest payload)
Large = dict[int | None, int]  #: channels sent as transfers of several frames -> longest event


def add_arguments(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument("-o", "--output", metavar="FILE.dbc", required=True, help="the DBC to write")
    source = cmd.add_mutually_exclusive_group()
    source.add_argument(
        "--can", metavar="INTERFACE:CHANNEL[,key=value...]",
        help="the live bus: its CAN-ECB's database and the frames heard (default: $UPS_CAN)",
    )  # fmt: skip
    source.add_argument("--recording", metavar="FILE", help="the frames of a recording instead")
    cmd.add_argument("--db", default=None, help="CAN: the CAN-ECB's database (default: the bus's)")
    cmd.add_argument(
        "--listen-for", type=positive_float, default=2.0, metavar="S",
        help="CAN: seconds to listen for the frames in use (default 2)",
    )  # fmt: skip
    add_catalog(cmd)


def run(args: argparse.Namespace) -> int:
    import os

    from .._catalog import load_catalog
    from .._extras import require

    require("cantools", "tools", "ups dbc writes with cantools, which is not installed")
    catalog = load_catalog(args.catalog)
    if args.recording is not None:
        bindings, streams, large = _from_recording(args.recording)
    else:
        bus = args.can or os.environ.get("UPS_CAN") or None
        if bus is None:
            raise ConfigError(
                "which frames? give --can BUS (the live bus) or --recording FILE: a DBC names "
                "frames by their identifier, which holds the TxNode and etag chosen on the bus"
            )
        bindings, streams, large = _from_bus(bus, args.db, args.listen_for)
    database, skipped = build(bindings, streams, catalog)
    database.refresh()
    import cantools

    try:
        cantools.database.dump_file(database, args.output)
    except OSError as exc:
        raise ConfigError(f"cannot write {args.output}: {exc.strerror}") from None
    print(
        f"ups dbc: {len(database.messages)} messages in {args.output}"
        + (f"; left out: {skipped} streams on etags bound to no known channel" if skipped else ""),
        file=sys.stderr,
    )
    if large:
        print(f"ups dbc: left out: {_large(large, bindings, catalog)}", file=sys.stderr)
    return 0


def _large(large: Large, bindings: Bindings, catalog: Catalog) -> str:
    """The channels sent as transfers of several frames, by name, and why no DBC has them."""

    def name(uid: int | None) -> str:
        if uid is None:
            return "a channel bound to no known UID"
        return catalog.channel(uid).name or bindings.names.get(uid) or f"0x{uid:016x}"

    named = ", ".join(
        f"{name(uid)} ({size} B)" if size else name(uid)
        for uid, size in sorted(large.items(), key=lambda item: name(item[0]))
    )
    return (
        f"{len(large)} channel{'s' * (len(large) != 1)} larger than one frame: {named}. Their "
        "events go as transfers of several frames on etags from 0x3000, which no DBC message "
        "(one frame each) describes: cantools and SavvyCAN show those frames as unknown; "
        "'ups decode' reads them"
    )


def build(bindings: Bindings, streams: Streams, catalog: Catalog) -> tuple[Any, int]:
    """The cantools Database of ``streams``; returns it and how many were left out."""
    from cantools.database.can import Database, Message

    from .. import _canproto as p

    messages = []
    skipped = 0
    used: set[str] = set()
    for stream, (uid, size) in sorted(streams.items()):
        priority, txnode, etag = stream
        if uid is None:
            skipped += 1
            continue
        spec = catalog.get(uid)
        name = catalog.channel(uid).name or bindings.names.get(uid) or f"uid_{uid:016x}"
        base = re.sub(r"[^A-Za-z0-9_]", "_", name).strip("_") or "channel"  # DBC: ASCII
        if base[0].isdigit():
            base = f"ch_{base}"
        label = f"{base}_tx{txnode:02x}"
        if label in used:  # another priority, or names that differ only in what _ stands for
            label = next(
                f"{label}_{n}" for n in range(2, len(used) + 3) if f"{label}_{n}" not in used
            )
        used.add(label)
        node = bindings.txnodes.get(txnode)
        signals, length = _signals(spec, size)
        comment = f"UPS channel {name} (UID 0x{uid:016x}), etag 0x{etag:04x}, TxNode 0x{txnode:02x}"
        if node is not None:
            comment += f" (node 0x{node:016x})"
        messages.append(
            Message(
                frame_id=p.make_id(priority, txnode, etag), name=label, length=length,
                signals=signals, comment=comment, is_extended_frame=True,
                is_fd=length > p.CLASSIC_MAX_DATA, strict=False,
            )
        )  # fmt: skip
    return Database(messages=messages, strict=False), skipped


def _signals(spec: ChannelSpec | None, observed: int) -> tuple[list[Any], int]:
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    fields = () if spec is None else spec.fields
    if not fields or spec is None or spec.size is None:
        if observed > 8:
            return [], observed
        raw = Signal("raw", 0, 8 * observed) if observed else None
        return ([raw] if raw else []), observed
    signals = []
    at = 0
    little = spec.byte_order == "little"
    for f in fields:
        size = f.size or 0
        start = 8 * at if little else 8 * at + 7  # DBC numbers a Motorola signal by its MSB
        conversion = BaseConversion.factory(
            scale=f.scale, offset=f.offset, is_float=f.type in ("f32", "f64")
        )
        signals.append(
            Signal(
                f.name, start, 8 * size if f.type != "bool" else 1,
                byte_order="little_endian" if little else "big_endian",
                is_signed=f.type.startswith("i"), conversion=conversion, unit=f.unit or None,
            )
        )  # fmt: skip
        at += size
    return signals, at


def _from_recording(path: str) -> tuple[Bindings, Streams, Large]:
    from .decode import Tally, bindings_for, read

    bindings = bindings_for(path, None, None)
    streams: Streams = {}
    large: Large = {}
    for _, item in read(path, bindings, Tally()):
        _add(streams, large, item)
    return bindings, streams, large


def _add(streams: Streams, large: Large, ev: object) -> None:
    """One event of a stream: the channel it carried (its last, when bound anew) and the
    longest payload; a transfer (or a frame of one), to ``large``."""
    from .. import _canproto as p
    from .._bindings import Event, Fragment

    if isinstance(ev, Fragment) and ev.etag >= p.LARGE_FIRST_ETAG:
        large.setdefault(ev.uid, 0)
    if not isinstance(ev, Event):
        return
    if ev.etag >= p.LARGE_FIRST_ETAG:  # a transfer of several frames: no DBC message is one
        large[ev.uid] = max(large.get(ev.uid, 0), len(ev.data))
        return
    stream = (ev.priority, ev.txnode, ev.etag)
    uid, size = streams.get(stream, (ev.uid, 0))
    if ev.uid != uid:
        size = 0  # the etag was bound anew: the DBC is true of the bus as it is now
    streams[stream] = (ev.uid, max(size, len(ev.data)))


def _from_bus(bus: str, db: str | None, seconds: float) -> tuple[Bindings, Streams, Large]:
    import time

    from .._bindings import Bindings, default_db
    from .._canlink import open_bus

    bindings = Bindings()
    bindings.load_db(db if db is not None else default_db(bus))
    streams: Streams = {}
    large: Large = {}
    listener = open_bus(bus)
    try:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            msg = listener.recv(left)
            if msg is None or not msg.is_extended_id or msg.is_error_frame:
                continue
            item = bindings.read(msg.arbitration_id, bytes(msg.data), fd=msg.is_fd)
            _add(streams, large, item)
    finally:
        listener.shutdown()
    return bindings, streams, large
