"""``ups decode FILE``: a recording (``ups record``), or any candump or python-can log of a UPS
bus, in UPS terms: each event's channel, decoded payload, priority and publisher.

Which channel an etag carries is learned as the file is read: from its sidecar
(``FILE.ups.json``, written by ``ups record``) or ``--bindings``, from a CAN-ECB's database
(``--db``), and from the Bind, PUB_AT and SUB_AT frames in the file itself, each taking effect
where it stands. An event whose etag is bound by none of them is shown by its etag.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from .._cliargs import add_catalog
from .._errors import ConfigError

if TYPE_CHECKING:
    from .. import _canproto as p
    from .._bindings import Bindings, Event
    from .._catalog import Catalog

HELP = "print a recording or a candump/python-can log of a UPS bus in UPS terms"


def add_arguments(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument("file", metavar="FILE", help="a log python-can reads (.asc, .blf, .log ...)")
    cmd.add_argument(
        "--bindings", metavar="FILE", default=None,
        help="the recording's bindings (default: FILE.ups.json when it exists)",
    )  # fmt: skip
    cmd.add_argument("--db", default=None, help="a CAN-ECB's database, for etags bound before")
    add_catalog(cmd)
    cmd.add_argument("--management", action="store_true", help="print management frames too")
    cmd.add_argument("--json", action="store_true", help="one JSON object per line")


class Tally:
    """What reading a recording found, beyond its events (a plain class: ``ups --help``
    imports this module, and dataclasses is a heavy import)."""

    __slots__ = ("events", "foreign", "fragments", "management", "unbound")

    def __init__(self) -> None:
        self.events = 0
        self.management = 0
        self.foreign = 0  #: 11-bit, error and remote frames, malformed management frames
        self.unbound = 0  #: events on etags bound to no known channel
        self.fragments = 0  #: frames of transfers (events larger than one frame) before the last


def bindings_for(path: str, sidecar: str | None, db: str | None) -> Bindings:
    """The bindings a recording starts from: its sidecar (or ``sidecar``), a database."""
    from pathlib import Path

    from .._bindings import Bindings, sidecar_of

    if not Path(path).is_file():
        raise ConfigError(f"no such file: {path}")
    side = Path(sidecar) if sidecar is not None else sidecar_of(path)
    bindings = Bindings.load(side) if sidecar is not None or side.is_file() else Bindings()
    if db is not None:
        bindings.load_db(db)
    return bindings


def read(
    path: str, bindings: Bindings, tally: Tally
) -> Iterator[tuple[float, Event | p.Management]]:
    """The frames of a recording in order, read in UPS terms (``bindings`` learns as it goes);
    what is not UPS is counted in ``tally`` and left out."""
    import can

    from .._bindings import Event, Fragment

    try:
        reader = can.LogReader(path)
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
    except Exception as exc:  # a reader raises whatever its parser does: struct, zlib ...
        raise ConfigError(f"{path}: not a log python-can can read ({exc})") from None
    try:
        for msg in reader:
            if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
                tally.foreign += 1
                continue
            item = bindings.read(
                msg.arbitration_id, bytes(msg.data), fd=msg.is_fd, now=msg.timestamp
            )
            if item is None:
                tally.foreign += 1
            elif isinstance(item, Fragment):
                tally.fragments += 1
            elif isinstance(item, Event):
                tally.events += 1
                tally.unbound += item.uid is None
                yield msg.timestamp, item
            else:
                tally.management += 1
                yield msg.timestamp, item
    except Exception as exc:  # a corrupt or cut file: python-can's parsers raise anything
        raise ConfigError(
            f"{path}: not a log python-can can read, or damaged after {tally.events} events "
            f"({type(exc).__name__}: {exc})"
        ) from None
    finally:
        stop = getattr(reader, "stop", None)
        if stop is not None:
            stop()


def run(args: argparse.Namespace) -> int:
    import json

    from .._bindings import Event
    from .._catalog import load_catalog

    bindings = bindings_for(args.file, args.bindings, args.db)
    catalog = load_catalog(args.catalog)
    tally = Tally()
    names = bindings.names
    for timestamp, item in read(args.file, bindings, tally):
        if isinstance(item, Event):
            print(_event_line(timestamp, item, catalog, names, bindings, args.json))
        elif args.management:
            if args.json:
                print(json.dumps({"time": timestamp, "management": repr(item)}))
            else:
                print(f"{timestamp:.6f}  [{_management(item, catalog, names)}]")
    print(
        f"ups decode: {tally.events} events ({tally.unbound} on etags bound to no known "
        f"channel), {tally.management} management frames, {tally.foreign} frames not UPS",
        file=sys.stderr,
    )
    return 0


def channel_label(uid: int | None, etag: int, catalog: Catalog, names: dict[int, str]) -> str:
    if uid is None:
        return f"etag 0x{etag:04x}"
    return catalog.channel(uid).name or names.get(uid) or f"0x{uid:016x}"


def _event_line(
    timestamp: float,
    ev: Event,
    catalog: Catalog,
    names: dict[int, str],
    bindings: Bindings,
    as_json: bool,
) -> str:
    import json

    node = bindings.txnodes.get(ev.txnode)
    if as_json:
        doc: dict[str, Any] = {
            "time": timestamp,
            "uid": None if ev.uid is None else f"0x{ev.uid:016x}",
            "channel": None if ev.uid is None else channel_label(ev.uid, ev.etag, catalog, names),
            "etag": f"0x{ev.etag:04x}",
            "data": ev.data.hex(),
            "values": None if ev.uid is None else catalog.decode(ev.uid, ev.data),
            "priority": ev.priority,
            "txnode": f"0x{ev.txnode:02x}",
            "node_id": None if node is None else f"0x{node:016x}",
        }
        if isinstance(doc["values"], dict):  # bytes fields as hex: JSON has no bytes
            doc["values"] = {
                k: v.hex() if isinstance(v, bytes) else v for k, v in doc["values"].items()
            }
        return json.dumps(doc)
    label = channel_label(ev.uid, ev.etag, catalog, names)
    value = catalog.format(ev.uid, ev.data) if ev.uid is not None else ev.data.hex() or "-"
    return f"{timestamp:.6f}  {label}  {value}  prio={ev.priority}  from=0x{ev.txnode:02x}"


def _management(item: p.Management, catalog: Catalog, names: dict[int, str]) -> str:
    from .. import _canproto as p

    if isinstance(item, p.Bind):
        return f"Bind etag 0x{item.etag:04x} = {channel_label(item.uid, item.etag, catalog, names)}"
    if isinstance(item, p.Holds):
        what = "publishes" if item.publish else "subscribes to"
        label = channel_label(item.uid, item.etag, catalog, names)
        return f"TxNode 0x{item.txnode:02x} {what} {label} (etag 0x{item.etag:04x})"
    if isinstance(item, p.Assign):
        return f"Assign TxNode 0x{item.txnode:02x} to node 0x{item.node_id:016x}"
    if isinstance(item, p.Request):
        who = f"TxNode 0x{item.txnode:02x}"
        if item.kind == p.CLAIM:
            return f"{who} claims it is node 0x{item.value:016x}"
        what = {p.PUB_BIND: "asks to publish on", p.SUB_BIND: "asks to subscribe to",
                p.UNSUB: "no longer subscribes to"}[item.kind]  # fmt: skip
        return f"{who} {what} {channel_label(item.value, 0, catalog, names)}"
    if isinstance(item, p.Declare):
        return (
            f"TxNode 0x{item.txnode:02x} declares etag 0x{item.etag:04x} real-time: "
            f"{item.size_bytes} bytes every {item.period / 10} ms, due in {item.deadline / 10} ms"
        )
    if isinstance(item, p.Grant):
        return (
            f"Grant: TxNode 0x{item.txnode:02x} on etag 0x{item.etag:04x} at priority "
            f"0x{item.priority:02x}"
        )
    return repr(item)
