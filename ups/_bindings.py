"""What a listener needs to read a UPS bus: which channel each etag carries, which node each
TxNode is. Learned from the CAN-ECB's database, from the management frames on the bus (Bind,
PUB_AT/SUB_AT, Assign) and from a recording's sidecar file.

The tools (``ls``, ``record``, ``decode``, ``replay``, ``monitor``, ``dbc``, ``console``) share
it. A frame reads as one of three things: a management frame (``Management``), an event
(``Event``: priority, TxNode, etag, payload and the channel UID when the etag is bound), or
foreign traffic (standard 11-bit ids, error frames, malformed management frames). Frames of
transfers (events larger than one frame) are reassembled: each reads as a ``Fragment`` until
the last, which reads as the whole ``Event``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import _canproto as p
from . import _cantransfer as t
from ._errors import ConfigError, DecodeError

SIDECAR_FORMAT = "ups-bindings/1"
SIDECAR_SUFFIX = ".ups.json"  #: next to a recording: capture.asc -> capture.asc.ups.json


@dataclass(frozen=True, slots=True)
class Event:
    """An event frame: ``uid`` is None when the etag's channel is not known (yet)."""

    priority: int
    txnode: int
    etag: int
    uid: int | None
    data: bytes


@dataclass(frozen=True, slots=True)
class Fragment:
    """A frame of a transfer that is not (yet) a whole event."""

    priority: int
    txnode: int
    etag: int
    uid: int | None


@dataclass
class Bindings:
    """etag -> channel UID and TxNode -> node id of one bus (or of one recording)."""

    etags: dict[int, int] = field(default_factory=dict)
    txnodes: dict[int, int] = field(default_factory=dict)
    names: dict[int, str] = field(default_factory=dict)  #: UID -> name, when known
    network: str = "can"  #: "can", or "tcp" for a recording of a TCP/IP network
    transfers: t.Reassembler = field(default_factory=t.Reassembler, repr=False, compare=False)

    def read(
        self, can_id: int, data: bytes, extended: bool = True, fd: bool = False, now: float = 0.0
    ) -> Event | Fragment | p.Management | None:
        """Read one frame (``fd``: a CAN FD frame, received at ``now``), learning from it; None
        for foreign or malformed traffic. Lost transfers are counted in ``transfers.lost``."""
        if not extended:
            return None
        if p.is_management(can_id):
            try:
                msg = p.decode(can_id, bytes(data))
            except DecodeError:
                return None
            self.learn(msg)
            return msg
        priority, txnode, etag = p.split_id(can_id)
        if etag < p.LARGE_FIRST_ETAG:
            if len(data) > p.CLASSIC_MAX_DATA:
                return None
            return Event(priority, txnode, etag, self.etags.get(etag), bytes(data))
        event = self.transfers.feed((txnode, etag), bytes(data), fd, t.max_size(etag), now)
        if event is None:
            return Fragment(priority, txnode, etag, self.etags.get(etag))
        return Event(priority, txnode, etag, self.etags.get(etag), event)

    def learn(self, msg: p.Management) -> None:
        if isinstance(msg, p.Bind | p.Holds):
            self.etags[msg.etag] = msg.uid
        elif isinstance(msg, p.Assign):
            for txnode, node_id in list(self.txnodes.items()):
                if node_id == msg.node_id and txnode != msg.txnode:
                    del self.txnodes[txnode]
            self.txnodes[msg.txnode] = msg.node_id

    def load_bus_db(self, bus: str, db: str | Path | None) -> None:
        """Add the tables of ``bus``'s CAN-ECB: from ``db`` (which must exist), else from the
        bus's default file when there is one on this host."""
        path = db if db is not None else default_db(bus)
        if db is not None or Path(path).is_file():
            self.load_db(path)

    def etag_of(self, uid: int) -> int | None:
        return next((e for e, u in self.etags.items() if u == uid), None)

    def load_db(self, db: str | Path) -> None:
        """Add the tables of a CAN-ECB's database, opened read-only (the CAN-ECB may run)."""
        import sqlite3

        if not Path(db).is_file():
            raise ConfigError(f"no CAN-ECB database at {db}: give --db, on the CAN-ECB's host")
        try:
            with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as conn:
                txnodes = [(int(n, 16), t) for n, t in conn.execute("SELECT * FROM txnodes")]
                etags = [(int(u, 16), e) for u, e in conn.execute("SELECT * FROM etags")]
        except (sqlite3.Error, ValueError) as exc:
            raise ConfigError(f"cannot read the CAN-ECB database {db}: {exc}") from None
        for node_id, txnode in txnodes:
            self.txnodes[txnode] = node_id
        for uid, etag in etags:
            self.etags[etag] = uid

    def to_json(self) -> dict[str, Any]:
        return {
            "format": SIDECAR_FORMAT,
            "network": self.network,
            "etags": {f"0x{e:04x}": f"0x{u:016x}" for e, u in sorted(self.etags.items())},
            "txnodes": {f"0x{t:02x}": f"0x{n:016x}" for t, n in sorted(self.txnodes.items())},
            "names": {f"0x{u:016x}": n for u, n in sorted(self.names.items())},
        }

    @classmethod
    def from_json(cls, doc: Any, source: str = "bindings") -> Bindings:
        try:
            if doc.get("format") != SIDECAR_FORMAT:
                raise ConfigError(f"{source}: not a UPS bindings file ({SIDECAR_FORMAT})")
            return cls(
                {_etag(e): _u64(u) for e, u in doc["etags"].items()},
                {_txnode(t): _u64(n) for t, n in doc["txnodes"].items()},
                {_u64(u): _name(n) for u, n in doc.get("names", {}).items()},
                str(doc.get("network", "can")),
            )
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: malformed bindings ({exc})") from None

    def save(self, path: str | Path) -> None:
        tmp = Path(f"{path}.tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> Bindings:
        try:
            doc = json.loads(Path(path).read_text())
        except OSError as exc:
            raise ConfigError(f"cannot read {path}: {exc.strerror}") from None
        except ValueError as exc:
            raise ConfigError(f"{path}: not JSON ({exc})") from None
        return cls.from_json(doc, str(path))


def _etag(text: str) -> int:
    value = int(text, 16)
    if not p.FIRST_ETAG <= value <= p.LAST_ETAG:
        raise ValueError(f"etag {text} out of range")
    return value


def _u64(text: str) -> int:
    if not re.fullmatch(r"0x[0-9a-fA-F]{1,16}", text):
        raise ValueError(f"{text!r} is not 0x and 1..16 hex digits (a 64-bit id)")
    return int(text, 16)


def _name(text: Any) -> str:
    if not isinstance(text, str):
        raise ValueError(f"channel name {text!r} is not a string")
    return text


def _txnode(text: str) -> int:
    value = int(text, 16)
    if not 0 <= value < p.TXNODE_COUNT:
        raise ValueError(f"TxNode {text} out of range")
    return value


def state_dir() -> Path:
    """Where daemons keep their state: ``$UPS_STATE_DIR``, else ``$XDG_STATE_HOME/ups``, else
    ``~/.local/state/ups``."""
    if os.environ.get("UPS_STATE_DIR"):
        return Path(os.environ["UPS_STATE_DIR"])
    base = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
    return Path(base) / "ups"


def default_db(bus: str) -> Path:
    """The CAN-ECB database of bus ``bus`` (an ``INTERFACE:CHANNEL[,key=value]`` spec): one
    file per interface, channel and (for udp_multicast) port, so two buses never share one."""
    head, *options = bus.split(",")
    port = [o.replace(" ", "") for o in options if o.replace(" ", "").startswith("port=")]
    slug = re.sub(r"[^A-Za-z0-9.]+", "_", "_".join([head, *port])).strip("_")
    return state_dir() / f"can-ecb-{slug}.db"


def sidecar_of(recording: str | Path) -> Path:
    return Path(f"{recording}{SIDECAR_SUFFIX}")
