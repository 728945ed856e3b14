"""The map file: which bytes of which EtherCAT slave's process data carry which UPS channel's
fields (TOML, in the style of the JAUS mapping)::

    catalog = "robot.toml"       # the channel catalog (payload layouts), relative to this file
    cycle = 0.002                # seconds between two process-data exchanges (--cycle overrides)
    timeout = 0.5                # an output's channel silent this long: its safe value is written
    status = "ethercat/status"   # the channel the segment's status is published on, once a second

    [slave.1]                    # the first slave in line order
    vendor = 0x2                 # its identity, as its SII EEPROM says (revision: optional)
    product = 0x7d23052
    outputs = [                  # bytes the master writes, from a channel's latest event
      { channel = "robot/max-speed", field = "limit", byte = 0, type = "i16", scale = 0.01,
        safe = 0.0 },
    ]
    inputs = [                   # bytes the slave returns, published on a channel
      { channel = "robot/bumper", field = "pressed", byte = 0, type = "u8", publish = "change" },
    ]

``byte`` is the position in that slave's output or input image, little-endian as EtherCAT is;
``type`` one of the catalog's fixed types; the channel's field is ``raw * scale + offset`` (as a
catalog converts). ``safe`` (a value of the field, default the one whose raw value is 0) is
written while the channel is silent, and before its first event. Inputs publish on ``change``
(default) or ``every`` K cycles; every field of an input channel comes from some entry, and the
entries of one channel agree on ``publish``, ``every`` and ``priority``. :func:`load_map` checks
all of it and raises :class:`MapError` naming the file and line of the first problem; the
sizes of the slaves' images are checked when the slaves are found (:meth:`SlaveMap.check`).
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ups import ConfigError, parse_channel
from ups._catalog import Catalog, ChannelSpec
from ups._tomlfile import read_toml

#: process-data types and their struct codes (little-endian)
TYPES = {
    "u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i", "u64": "Q",
    "i64": "q", "f32": "f", "f64": "d", "bool": "?",
}  # fmt: skip
DEFAULT_CYCLE = 0.002
DEFAULT_TIMEOUT = 0.5
DEFAULT_STATUS = "ethercat/status"
MIN_CYCLE = 0.0005  #: a shorter cycle than this is refused (a Python master cannot keep it)
MAX_CYCLE = 1.0  #: a longer cycle than this is refused (no slave's watchdog waits so long)
MAX_TIMEOUT = 3600.0  #: the longest silence before outputs go safe (an hour)
MAX_EVERY = 1_000_000  #: the most cycles between two events of a channel published "every"
_TOP = {"catalog", "cycle", "timeout", "status", "slave"}
_SLAVE = {"vendor", "product", "revision", "outputs", "inputs"}
_COMMON = {"channel", "field", "byte", "type", "scale", "offset"}
_OUTPUT = _COMMON | {"safe"}
_INPUT = _COMMON | {"publish", "every", "priority"}


class MapError(ConfigError):
    """A map file that cannot be used; ``str()`` starts with ``FILE:LINE:``."""


@dataclass(frozen=True, slots=True)
class Entry:
    """One field of a channel at ``byte`` of a slave's image: ``field = raw * scale + offset``."""

    slave: int
    spec: ChannelSpec
    field: str
    byte: int
    type: str
    scale: float
    offset: float
    line: int

    @property
    def size(self) -> int:
        return struct.calcsize(TYPES[self.type])

    def pack(self, value: float) -> tuple[bytes, bool]:
        """The raw bytes of the field's ``value``, and whether it was saturated to fit the
        type (a value out of its range, or not a number: 0)."""
        raw = (float(value) - self.offset) / self.scale
        code = "<" + TYPES[self.type]
        if self.type in ("f32", "f64"):
            try:
                return struct.pack(code, raw), False
            except OverflowError:  # beyond an f32
                return struct.pack(code, math.copysign(math.inf, raw)), True
        if self.type == "bool":
            return (b"\x01" if raw else b"\x00"), raw not in (0.0, 1.0)
        low, high = _limits(self.type)
        if math.isnan(raw):
            return struct.pack(code, 0), True
        whole = round(raw) if math.isfinite(raw) else (high if raw > 0 else low)
        fitted = min(max(whole, low), high)
        return struct.pack(code, fitted), fitted != whole or not math.isfinite(raw)

    def unpack(self, image: bytes) -> float:
        """The field's value from the slave's image."""
        (raw,) = struct.unpack_from("<" + TYPES[self.type], image, self.byte)
        return float(raw) * self.scale + self.offset


@dataclass(frozen=True, slots=True)
class Output(Entry):
    safe: bytes = b""  #: the raw bytes written while the channel is silent


@dataclass(frozen=True, slots=True)
class InputChannel:
    """A channel published from slaves' inputs: its entries cover every field."""

    spec: ChannelSpec
    entries: tuple[Entry, ...]
    every: int  #: publish every K cycles; 0: on change
    priority: int | None


@dataclass(frozen=True, slots=True)
class SlaveMap:
    position: int
    vendor: int
    product: int
    revision: int | None
    outputs: tuple[Output, ...]
    line: int

    def identity(self) -> str:
        rev = "" if self.revision is None else f" revision 0x{self.revision:08x}"
        return f"vendor 0x{self.vendor:08x} product 0x{self.product:08x}{rev}"


@dataclass(frozen=True, slots=True)
class EthercatMap:
    path: Path
    catalog: Catalog
    cycle: float
    timeout: float
    status: str
    slaves: dict[int, SlaveMap]
    inputs: tuple[InputChannel, ...]

    def output_channels(self) -> dict[ChannelSpec, list[Output]]:
        out: dict[ChannelSpec, list[Output]] = {}
        for slave in self.slaves.values():
            for entry in slave.outputs:
                out.setdefault(entry.spec, []).append(entry)
        return out


def load_map(path: str | Path) -> EthercatMap:
    """Read and check the map at ``path`` and the catalog it names."""
    path = Path(path)
    try:
        text, doc = read_toml(path, "the map")
    except ConfigError as exc:
        raise MapError(str(exc)) from None
    lines = _Lines(path, text)
    for key in doc:
        if key not in _TOP:
            raise lines.error(f"unknown key {key!r} ({', '.join(sorted(_TOP))})", key)
    if "catalog" not in doc:
        raise lines.error('no catalog: give catalog = "FILE"', None)
    try:
        catalog = Catalog.load(path.parent / str(doc["catalog"]))
    except ConfigError as exc:
        raise lines.error(str(exc), "catalog") from None
    cycle = _seconds(doc, "cycle", DEFAULT_CYCLE, lines, MAX_CYCLE)
    if cycle < MIN_CYCLE:
        raise lines.error(f"cycle: at least {MIN_CYCLE} s", "cycle")
    timeout = _seconds(doc, "timeout", DEFAULT_TIMEOUT, lines, MAX_TIMEOUT)
    status = doc.get("status", DEFAULT_STATUS)
    if not isinstance(status, str) or not status:
        raise lines.error("status: a channel name", "status")
    table = doc.get("slave")
    if not isinstance(table, dict) or not table:
        raise lines.error("no [slave.N] table", None)
    slaves: dict[int, SlaveMap] = {}
    inputs: list[tuple[Entry, str, int, int | None]] = []
    for key, entry in table.items():
        if not key.isdigit() or int(key) < 1:
            raise lines.error(f"[slave.{key}]: N is a position, 1 for the first slave", None,
                              f"slave.{key}")  # fmt: skip
        slaves[int(key)] = _slave(int(key), entry, catalog, lines, inputs)
    return EthercatMap(path, catalog, cycle, timeout, status, dict(sorted(slaves.items())),
                       _input_channels(inputs))  # fmt: skip


def _seconds(doc: dict[str, Any], key: str, default: float, lines: _Lines, most: float) -> float:
    value = doc.get(key, default)
    if not isinstance(value, int | float) or isinstance(value, bool) or not 0 < value <= most:
        raise lines.error(f"{key}: seconds, a number above 0 and at most {most:g}", key)
    return float(value)


def _slave(position: int, entry: Any, catalog: Catalog, lines: _Lines,
           inputs: list[tuple[Entry, str, int, int | None]]) -> SlaveMap:  # fmt: skip
    header = f"slave.{position}"

    def fail(text: str, key: str | None = None) -> MapError:
        return lines.error(f"[{header}]: {text}", key, header)

    if not isinstance(entry, dict):
        raise fail("must be a table")
    for key in entry:
        if key not in _SLAVE:
            raise fail(f"unknown key {key!r} ({', '.join(sorted(_SLAVE))})", key)
    ids: dict[str, int | None] = {}
    for key in ("vendor", "product", "revision"):
        value = entry.get(key)
        if value is None and key != "revision":
            raise fail(f"no {key}: the slave's identity (its SII EEPROM says it)")
        if value is not None and (not isinstance(value, int) or isinstance(value, bool)
                                  or not 0 <= value <= 0xFFFFFFFF):  # fmt: skip
            raise fail(f"{key}: a 32-bit number, e.g. 0x0000000{position}", key)
        ids[key] = value
    outputs: list[Output] = []
    taken: dict[int, int] = {}  # output byte -> the line that writes it
    for kind in ("outputs", "inputs"):
        items = entry.get(kind, [])
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise fail(f"{kind}: a list of tables {{ channel, field, byte, type, ... }}", kind)
        for n, item in enumerate(items):
            line = lines.entry(header, kind, n)
            where = f"{lines.path}:{line}: [{header}] {kind}[{n}]"
            base = _entry(position, item, catalog, kind, where, line)
            if kind == "inputs":
                inputs.append(_input_options(base, item, where))
                continue
            for b in range(base.byte, base.byte + base.size):
                if b in taken:
                    raise MapError(f"{where}: byte {b} is written by line {taken[b]} too")
                taken[b] = line
            safe = item.get("safe", base.offset)
            if not isinstance(safe, int | float) or isinstance(safe, bool):
                raise MapError(f"{where}: safe is a value of {base.field}, a number")
            raw, clipped = base.pack(safe)
            if clipped:
                raise MapError(f"{where}: safe {safe} does not fit a {base.type}")
            outputs.append(Output(position, base.spec, base.field, base.byte, base.type,
                                  base.scale, base.offset, line, safe=raw))  # fmt: skip
    vendor, product = ids["vendor"], ids["product"]
    assert vendor is not None and product is not None
    return SlaveMap(position, vendor, product, ids["revision"], tuple(outputs),
                    lines.line(header, None))  # fmt: skip


def _entry(position: int, item: dict[str, Any], catalog: Catalog, kind: str, where: str,
           line: int) -> Entry:  # fmt: skip
    known = _OUTPUT if kind == "outputs" else _INPUT
    for key in item:
        if key not in known:
            raise MapError(f"{where}: unknown key {key!r} ({', '.join(sorted(known))})")
    for key in ("channel", "field", "byte", "type"):
        if key not in item:
            raise MapError(f"{where}: no {key}")
    try:
        channel = parse_channel(str(item["channel"]))
    except ConfigError as exc:
        raise MapError(f"{where}: {exc}") from None
    spec = catalog.get(channel.uid)
    if spec is None or not spec.fields or spec.size is None:
        raise MapError(f"{where}: channel {item['channel']} has no fixed payload layout in the "
                       "catalog")  # fmt: skip
    names = {f.name: f for f in spec.fields}
    field = str(item["field"])
    if field not in names:
        raise MapError(f"{where}: {spec.channel} has no field {field!r} (it has: "
                       f"{', '.join(names)})")  # fmt: skip
    if names[field].type in ("str", "bytes"):
        raise MapError(f"{where}: {spec.channel}.{field} is not a number")
    kind_ = item["type"]
    if kind_ not in TYPES:
        raise MapError(f"{where}: type {kind_!r} is not one of {', '.join(TYPES)}")
    byte = item["byte"]
    if not isinstance(byte, int) or isinstance(byte, bool) or not 0 <= byte < 4096:
        raise MapError(f"{where}: byte is a position in the slave's image, 0 for the first")
    scale, offset = item.get("scale", 1.0), item.get("offset", 0.0)
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in (scale, offset)):
        raise MapError(f"{where}: scale and offset are numbers")
    if scale == 0 or not math.isfinite(scale) or not math.isfinite(offset):
        raise MapError(f"{where}: scale is a finite number other than 0, offset a finite one")
    return Entry(position, spec, field, byte, kind_, float(scale), float(offset), line)


def _input_options(base: Entry, item: dict[str, Any],
                   where: str) -> tuple[Entry, str, int, int | None]:  # fmt: skip
    publish = item.get("publish", "change")
    if publish not in ("change", "every"):
        raise MapError(f'{where}: publish is "change" or "every", not {publish!r}')
    every = item.get("every", 1 if publish == "every" else 0)
    if publish == "change" and "every" in item:
        raise MapError(f'{where}: every K goes with publish = "every"')
    if not isinstance(every, int) or isinstance(every, bool) or (publish == "every"
                                                                 and every < 1):  # fmt: skip
        raise MapError(f"{where}: every is a number of cycles, 1 or more")
    if every > MAX_EVERY:
        raise MapError(f"{where}: every is at most {MAX_EVERY} cycles")
    priority = item.get("priority")
    if priority is not None and (not isinstance(priority, int) or isinstance(priority, bool)
                                 or not 0 <= priority <= 255):  # fmt: skip
        raise MapError(f"{where}: priority is 0-255")
    return base, where, every, priority


def _input_channels(
    inputs: list[tuple[Entry, str, int, int | None]],
) -> tuple[InputChannel, ...]:
    by_channel: dict[ChannelSpec, list[tuple[Entry, str, int, int | None]]] = {}
    for one in inputs:
        by_channel.setdefault(one[0].spec, []).append(one)
    out = []
    for spec, found in by_channel.items():
        _, first_where, every, priority = found[0]
        seen: dict[str, str] = {}
        for entry, where, other_every, other_priority in found:
            if (other_every, other_priority) != (every, priority):
                raise MapError(f"{where}: {spec.channel}: publish, every and priority differ "
                               f"from {first_where.split(': [')[0]}")  # fmt: skip
            if entry.field in seen:
                raise MapError(f"{where}: {spec.channel}.{entry.field} comes from "
                               f"{seen[entry.field]} too")  # fmt: skip
            seen[entry.field] = where.split(": [")[0]
        missing = [f.name for f in spec.fields if f.name not in seen]
        if missing:
            raise MapError(f"{first_where}: field {missing[0]!r} of {spec.channel} comes from no "
                           "input")  # fmt: skip
        out.append(InputChannel(spec, tuple(f[0] for f in found), every, priority))
    return tuple(out)


def _limits(kind: str) -> tuple[int, int]:
    bits = struct.calcsize(TYPES[kind]) * 8
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if kind[0] == "i" else (0, (1 << bits) - 1)


class _Lines:
    """Lines of the file, to name where a problem is."""

    def __init__(self, path: Path, text: str) -> None:
        self.path = path
        self.lines = text.splitlines()

    def _section(self, header: str | None) -> tuple[int, int]:
        """The lines (first, end) of ``[header]``, or of the whole file."""
        if header is None:
            return 0, len(self.lines)
        pattern = re.compile(rf"^\s*\[\s*{re.escape(header)}\s*\]")
        start = next((i for i, ln in enumerate(self.lines) if pattern.match(ln)), 0)
        end = next((i for i in range(start + 1, len(self.lines))
                    if self.lines[i].lstrip().startswith("[") and "=" not in self.lines[i]),
                   len(self.lines))  # fmt: skip
        return start, end

    def line(self, header: str | None, key: str | None) -> int:
        start, end = self._section(header)
        if key is not None:
            pattern = re.compile(rf"^\s*\"?{re.escape(key)}\"?\s*=")
            for i in range(start, end):
                if pattern.match(self.lines[i]):
                    return i + 1
        return start + 1

    def entry(self, header: str, key: str, index: int) -> int:
        """The line of the ``index``-th inline table of the list ``key`` in ``[header]``."""
        first = self.line(header, key) - 1
        _, end = self._section(header)
        seen = -1
        for i in range(first, end):
            text = self.lines[i].split("#", 1)[0]
            if i > first and re.match(r"^\s*\w+\s*=", text) and "{" not in text.split("=")[0]:
                break  # the next key of the table
            for _ in re.finditer(r"\{", text):
                seen += 1
                if seen == index:
                    return i + 1
        return first + 1

    def error(self, text: str, key: str | None, header: str | None = None) -> MapError:
        return MapError(f"{self.path}:{self.line(header, key)}: {text}")
