"""The mapping file: which UPS channel each JAUS message stands for, field by field (paper
003's textual mapping of application messages, in TOML).

::

    catalog = "robots.toml"              # the channel catalog, relative to this file

    [message.SetWrenchEffort]            # a command: JAUS -> UPS
    channel = "robot/max-speed"          # a catalog channel, by name or 0xUID
    fields.propulsive_linear_x = { field = "limit", scale = 2.0 }   # ups = jaus*scale + offset
    constants = {}                       # UPS fields given a fixed value
    ignore = ["propulsive_rotational_z"] # JAUS fields deliberately not carried

    [message.ReportGlobalPose]           # a report: UPS -> JAUS
    channel = "robot/pose"
    rate = 10.0                          # the most reports per second a connection gets
    fields.latitude = { field = "lat" }
    timestamp = "event"                  # the time stamp: when the channel's event arrived

    [authority]                          # the most authority granted per source address range
    "127.0.0.0/8" = 255                  # (the longest prefix holding the address decides;
    "192.168.1.0/24" = 100               # an address in no range takes no control)

A command (``Set…``, ``Request…``) is published on its channel from the JAUS fields; every
field of the channel must then be mapped or constant. A report (``Report…``) is made from the
channel's latest event; every field of the JAUS message must then be mapped, constant or
ignored, or for a time stamp filled (``timestamp = "event"``: when the channel's event arrived,
UTC). Without ``[authority]`` any address may ask for any authority. :func:`load_mapping`
checks all of it once, at start, and raises
:class:`MappingError` naming the file and line of the first problem; the result converts
with plain arithmetic, nothing read from the file on the way.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import re
import typing
from collections.abc import Mapping as MappingABC
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ups import ConfigError, parse_channel
from ups._catalog import Catalog, ChannelSpec
from ups._tomlfile import read_toml

from ._access import AuthorityCaps
from ._messages import TYPES
from ._payloads import TimeStamp

#: the JAUS messages a mapping can name: the payload classes with fields
MESSAGES: dict[str, type] = {
    cls.__name__: cls
    for cls in TYPES
    if cls.__name__.startswith(("Set", "Request", "Report", "ClearEmergency"))
    and dataclasses.fields(cls)
    and getattr(cls, "MAPPABLE", True)
}  # fmt: skip
MAX_RATE = 1000.0  #: reports per second a mapped report may ask for, at most
_NUMERIC = ("u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64", "f32", "f64")


class MappingError(ConfigError):
    """A mapping file that cannot be used; ``str()`` starts with ``FILE:LINE:``."""


@dataclass(frozen=True, slots=True)
class FieldMap:
    """``ups = jaus * scale + offset``, and back."""

    jaus: str
    ups: str
    scale: float = 1.0
    offset: float = 0.0
    integer: bool = False  #: the JAUS field holds an integer: a report rounds to it


@dataclass(frozen=True, slots=True)
class MessageMap:
    message: str
    command: bool  #: JAUS -> UPS (a command); else UPS -> JAUS (a report)
    channel: ChannelSpec
    fields: tuple[FieldMap, ...]
    constants: MappingABC[str, float]
    ignored: frozenset[str]
    rate: float | None
    line: int
    stamped: bool = False  #: a report's time stamp is when its event arrived

    def to_ups(self, payload: Any) -> bytes:
        """A command's payload as the channel's event."""
        values = dict(self.constants)
        for f in self.fields:
            value = getattr(payload, f.jaus)
            values[f.ups] = 0.0 if value is None else value * f.scale + f.offset
        return self.channel.encode(values)

    def from_ups(self, data: bytes, when: float | None = None) -> Any:
        """A report's payload from the channel's event (that arrived at ``when``, seconds since
        the epoch: the time stamp, when the mapping asks for one)."""
        values = self.channel.decode(data)
        out: dict[str, Any] = dict(self.constants)
        if self.stamped and when is not None:
            out["timestamp"] = TimeStamp.at(when)
        for f in self.fields:
            value = (float(values[f.ups]) - f.offset) / f.scale
            out[f.jaus] = round(value) if f.integer else value
        return MESSAGES[self.message](**out)


class Bridge(dict[str, MessageMap]):
    """JAUS message name -> its mapping; ``authority``: the caps of the ``[authority]`` table
    (None without one: any address, any authority)."""

    authority: AuthorityCaps | None = None


def load_mapping(path: str | Path, catalog: Catalog | None = None) -> Bridge:
    """Read and check the mapping at ``path``; its ``catalog`` key (relative to the file)
    names the channel catalog unless one is given."""
    path = Path(path)
    try:
        text, doc = read_toml(path, "the mapping")
    except ConfigError as exc:
        raise MappingError(str(exc)) from None
    where = _Where(path, text)
    unknown = set(doc) - {"catalog", "message", "authority"}
    if unknown:
        key = sorted(unknown)[0]
        raise where.error(f"unknown key {key!r} (catalog, message, authority)", key)
    if catalog is None:
        if "catalog" not in doc:
            raise where.error('no catalog: give catalog = "FILE" or --catalog', None)
        try:
            catalog = Catalog.load(path.parent / str(doc["catalog"]))
        except ConfigError as exc:
            raise where.error(str(exc), "catalog") from None
    messages = doc.get("message", {})
    if not isinstance(messages, dict) or not messages:
        raise where.error("no [message.NAME] table", None)
    bridge = Bridge(
        (name, _message(name, entry, catalog, where)) for name, entry in messages.items()
    )
    if "authority" in doc:
        bridge.authority = _authority(doc["authority"], where)
    return bridge


def _authority(table: Any, where: _Where) -> AuthorityCaps:
    """``[authority]``: address ranges (CIDR) and the most authority (0-255) each is granted."""

    def fail(text: str, key: str | None = None) -> MappingError:
        return where.error(f"[authority]: {text}", key, header="authority")

    if not isinstance(table, dict) or not table:
        raise fail('give address ranges and their most authority, e.g. "10.0.0.0/8" = 100',
                   "authority")  # fmt: skip
    ranges = []
    for key, cap in table.items():
        try:
            network = ipaddress.ip_network(key)
        except ValueError as exc:
            raise fail(f"{key!r} is not an address range: {exc}", key) from None
        if not isinstance(cap, int) or isinstance(cap, bool) or not 0 <= cap <= 255:
            raise fail(f"{key}: an authority is 0-255, not {cap!r}", key)
        ranges.append((network, cap))
    return AuthorityCaps(tuple(ranges))


class _Where:
    """Lines of the file, to name where a problem is."""

    def __init__(self, path: Path, text: str) -> None:
        self.path = path
        self.lines = text.splitlines()

    def line(self, section: str | None, key: str | None, header: str | None = None) -> int:
        """The line of ``key`` in ``[message.SECTION]`` (or in the table ``[HEADER]``)."""
        start = 0
        table = header or (section and rf"message\.\"?{re.escape(section)}\"?")
        if table:
            found = re.compile(rf"^\s*\[\s*{table}\s*\]")
            start = next((i for i, ln in enumerate(self.lines) if found.match(ln)), 0)
        if key is None:
            return start + 1
        pattern = re.compile(rf"(^|[\s.{{,\[\"]){re.escape(key)}\"?\s*[=,\]\}}]")
        for i in range(start, len(self.lines)):
            if i > start and table and self.lines[i].lstrip().startswith("["):
                break
            if pattern.search(self.lines[i]):
                return i + 1
        return start + 1

    def error(
        self, text: str, key: str | None, section: str | None = None, header: str | None = None
    ) -> MappingError:
        return MappingError(f"{self.path}:{self.line(section, key, header)}: {text}")


def _message(name: str, entry: Any, catalog: Catalog, where: _Where) -> MessageMap:
    def fail(text: str, key: str | None = None) -> MappingError:
        return where.error(f"[message.{name}]: {text}", key, name)

    cls = MESSAGES.get(name)
    if cls is None:
        raise fail(f"unknown JAUS message {name!r} (known: {', '.join(sorted(MESSAGES))})")
    if not isinstance(entry, dict):
        raise fail("must be a table")
    extra = set(entry) - {"channel", "fields", "constants", "ignore", "rate", "timestamp"}
    if extra:
        raise fail(f"unknown key {sorted(extra)[0]!r}", sorted(extra)[0])
    if "channel" not in entry:
        raise fail("no channel")
    try:
        channel = parse_channel(str(entry["channel"]))
    except ConfigError as exc:
        raise fail(str(exc), "channel") from None
    spec = catalog.get(channel.uid)
    if spec is None or not spec.fields:
        raise fail(f"channel {entry['channel']} has no payload layout in the catalog", "channel")
    ups_fields = {f.name: f for f in spec.fields}
    hints = typing.get_type_hints(cls)
    jaus_fields = {f.name: hints[f.name] for f in dataclasses.fields(cls)}
    command = not name.startswith("Report")
    maps = []
    raw_fields = entry.get("fields", {})
    if not isinstance(raw_fields, dict):
        raise fail("fields must be a table", "fields")
    for jaus_name, target in raw_fields.items():
        if jaus_name not in jaus_fields:
            raise fail(f"{name} has no field {jaus_name!r} (it has: "
                       f"{', '.join(jaus_fields)})", jaus_name)  # fmt: skip
        if isinstance(target, str):
            target = {"field": target}
        if not isinstance(target, dict) or "field" not in target:
            raise fail(f'fields.{jaus_name}: give {{ field = "NAME", scale, offset }}', jaus_name)
        ups_name = str(target["field"])
        if ups_name not in ups_fields:
            raise fail(f"channel {spec.channel} has no field {ups_name!r} (it has: "
                       f"{', '.join(ups_fields)})", jaus_name)  # fmt: skip
        if not _numeric(jaus_fields[jaus_name]) or ups_fields[ups_name].type not in _NUMERIC:
            raise fail(f"type mismatch: {name}.{jaus_name} ({_show(jaus_fields[jaus_name])}) "
                       f"and {spec.channel}.{ups_name} ({ups_fields[ups_name].type})",
                       jaus_name)  # fmt: skip
        scale, offset = target.get("scale", 1.0), target.get("offset", 0.0)
        if not all(_finite(v) for v in (scale, offset)):
            raise fail(f"fields.{jaus_name}: scale and offset are finite numbers", jaus_name)
        if scale == 0:
            raise fail(f"fields.{jaus_name}: scale 0 cannot be turned back", jaus_name)
        integer = _integer(jaus_fields[jaus_name])
        maps.append(FieldMap(jaus_name, ups_name, float(scale), float(offset), integer))
    constants = entry.get("constants", {})
    ignored = entry.get("ignore", [])
    if not isinstance(constants, dict) or not isinstance(ignored, list):
        raise fail("constants is a table, ignore a list", "constants")
    side = ups_fields if command else jaus_fields
    for key, value in constants.items():
        if key not in side:
            raise fail(f"constant {key!r} is not a field of "
                       f"{spec.channel if command else name}", key)  # fmt: skip
        if not _finite(value):
            raise fail(f"constant {key!r} must be a finite number", key)
        if not command and _integer(jaus_fields[key]) and value != int(value):
            raise fail(f"constant {key!r}: {name}.{key} is an integer, not {value}", key)
    for key in ignored:
        if key not in jaus_fields:
            raise fail(f"ignore: {name} has no field {key!r}", str(key))
    stamped = _stamped(entry.get("timestamp"), command, jaus_fields, set(constants) | set(ignored),
                       fail)  # fmt: skip
    covered = {m.ups for m in maps} if command else {m.jaus for m in maps} | stamped
    if command:
        missing = sorted(set(ups_fields) - covered - set(constants))
    else:
        missing = sorted(set(jaus_fields) - covered - set(constants) - set(ignored))
    if missing:
        what = f"field {missing[0]!r} of {spec.channel if command else name}"
        raise fail(f"{what} is neither mapped, constant{'' if command else ' nor ignored'}")
    rate = entry.get("rate")
    if rate is not None and (not _finite(rate) or not 0 < rate <= MAX_RATE):
        raise fail(f"rate must be a number of reports per second above 0, at most {MAX_RATE:g}",
                   "rate")  # fmt: skip
    if not command:  # an integer JAUS field's constant is given as one
        constants = {k: int(v) if _integer(jaus_fields[k]) else v for k, v in constants.items()}
    return MessageMap(
        name, command, spec, tuple(maps), dict(constants), frozenset(map(str, ignored)),
        None if rate is None else float(rate), where.line(name, None), bool(stamped),
    )  # fmt: skip


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _stamped(kind: Any, command: bool, jaus_fields: dict[str, Any], elsewhere: set[str],
             fail: Any) -> set[str]:  # fmt: skip
    """``{"timestamp"}`` when a report's time stamp is filled (``timestamp = "event"``)."""
    if kind is None:
        return set()
    if command or "timestamp" not in jaus_fields:
        raise fail("timestamp: only a report with a time stamp has one", "timestamp")
    if kind != "event":
        raise fail('timestamp = "event" (when the channel\'s event arrived) is the one kind',
                   "timestamp")  # fmt: skip
    if "timestamp" in elsewhere:
        raise fail("timestamp is filled: it is neither constant nor ignored", "timestamp")
    return {"timestamp"}


def _numeric(hint: Any) -> bool:
    args = typing.get_args(hint) or (hint,)
    return all(a in (int, float, type(None)) or (isinstance(a, type) and issubclass(a, int))
               for a in args)  # fmt: skip


def _integer(hint: Any) -> bool:
    """Whether a JAUS field holds an integer (int, an IntEnum, either or None)."""
    args = [a for a in typing.get_args(hint) or (hint,) if a is not type(None)]
    return all(isinstance(a, type) and issubclass(a, int) for a in args)


def _show(hint: Any) -> str:
    return "text" if hint is str else getattr(hint, "__name__", str(hint))
