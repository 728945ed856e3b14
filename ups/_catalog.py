"""The channel catalog: what the channels of a system are called and what their bytes mean.

A catalog is a TOML file with one table per channel, keyed by its name (or by its UID as
``0x`` + hex when it has no name)::

    [channel."robot/speed"]
    description = "wheel speeds"
    period = 0.01                # seconds between events, as published
    priority = 0x40              # CAN priority (0 highest .. 255)
    byte_order = "little"        # of every field (default little)
    fields = [
        { name = "left", type = "i16", scale = 0.001, unit = "m/s" },
        { name = "right", type = "i16", scale = 0.001, unit = "m/s" },
    ]
    realtime = { deadline = 0.01, jitter = 0.001 }   # a real-time declaration (CAN)

Field types: ``u8 i8 u16 i16 u32 i32 u64 i64 f32 f64 bool`` (fixed size, back to back from
byte 0), and as the last field only ``str`` (UTF-8) or ``bytes``: the rest of the payload. A
numeric field's value is ``raw * scale + offset`` (scale 1, offset 0 by default).

The tools (``ups ls``, ``monitor``, ``decode``, ``dbc``, ``console``, ``analyze``) take it as
``--catalog FILE`` or ``$UPS_CATALOG``. Names on CAN come only from here: CAN frames carry etags.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ._channel import Channel, parse_channel
from ._errors import ConfigError, DecodeError, UpsError

if TYPE_CHECKING:
    from pathlib import Path

_FIXED = {
    "u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i",
    "u64": "Q", "i64": "q", "f32": "f", "f64": "d", "bool": "?",
}  # fmt: skip
_TAIL = ("str", "bytes")  #: the rest of the payload; only as the last field
FIELD_TYPES = (*_FIXED, *_TAIL)
MAX_CHANNELS = 16368  #: a catalog describes at most as many channels as a CAN bus has etags
_KEYS = {"description", "period", "priority", "byte_order", "fields", "realtime"}
_FIELD_KEYS = {"name", "type", "unit", "scale", "offset"}

Value = int | float | bool | str | bytes


@dataclass(frozen=True, slots=True)
class Field:
    """One field of a payload layout."""

    name: str
    type: str
    unit: str = ""
    scale: float = 1.0
    offset: float = 0.0

    @property
    def size(self) -> int | None:
        """Bytes on the wire; None for the rest of the payload (``str``, ``bytes``)."""
        code = _FIXED.get(self.type)
        return None if code is None else struct.calcsize(code)

    @property
    def scaled(self) -> bool:
        return self.scale != 1.0 or self.offset != 0.0


@dataclass(frozen=True, slots=True)
class Realtime:
    """A real-time declaration: at most one event per ``period`` s, released up to ``jitter``
    s late, due within ``deadline`` s."""

    period: float
    deadline: float
    jitter: float = 0.0


@dataclass(frozen=True, slots=True)
class ChannelSpec:
    """What the catalog says about one channel."""

    channel: Channel
    description: str = ""
    period: float | None = None
    priority: int | None = None
    byte_order: str = "little"
    fields: tuple[Field, ...] = ()
    realtime: Realtime | None = None

    @property
    def uid(self) -> int:
        return self.channel.uid

    @property
    def name(self) -> str | None:
        return self.channel.name

    @property
    def size(self) -> int | None:
        """The payload's size in bytes when every field is fixed, else None."""
        if any(f.size is None for f in self.fields):
            return None
        return sum(f.size or 0 for f in self.fields)

    def decode(self, data: bytes) -> dict[str, Value]:
        """The payload's fields by name; raises DecodeError when it does not fit the layout."""
        out: dict[str, Value] = {}
        at = 0
        order = "<" if self.byte_order == "little" else ">"
        for f in self.fields:
            if f.size is None:
                rest = data[at:]
                at = len(data)
                if f.type == "bytes":
                    out[f.name] = bytes(rest)
                else:
                    try:
                        out[f.name] = rest.decode("utf-8")
                    except UnicodeDecodeError:
                        raise DecodeError(f"{self.channel}: field {f.name} is not UTF-8") from None
                continue
            if at + f.size > len(data):
                raise DecodeError(
                    f"{self.channel}: {len(data)} bytes, the layout needs {self._need()}"
                )
            (raw,) = struct.unpack_from(order + _FIXED[f.type], data, at)
            at += f.size
            out[f.name] = raw * f.scale + f.offset if f.scaled else raw
        if at != len(data):
            raise DecodeError(f"{self.channel}: {len(data)} bytes, the layout needs {self._need()}")
        return out

    def encode(self, values: Mapping[str, Any]) -> bytes:
        """The payload of ``values`` (every field by name); raises ConfigError for a missing,
        unknown or out-of-range value."""
        unknown = set(values) - {f.name for f in self.fields}
        if unknown:
            raise ConfigError(f"{self.channel} has no field {', '.join(sorted(unknown))}")
        order = "<" if self.byte_order == "little" else ">"
        parts = []
        for f in self.fields:
            if f.name not in values:
                raise ConfigError(f"{self.channel}: a value for {f.name} is missing")
            value = values[f.name]
            try:
                if f.type == "bytes":
                    parts.append(bytes.fromhex(value) if isinstance(value, str) else bytes(value))
                    continue
                if f.type == "str":
                    parts.append(str(value).encode("utf-8"))
                    continue
                raw = _raw(f, value)
                parts.append(struct.pack(order + _FIXED[f.type], raw))
            except (struct.error, TypeError, ValueError, OverflowError) as exc:
                raise ConfigError(f"{self.channel}: {f.name}={value!r}: {exc}") from None
        return b"".join(parts)

    def format(self, data: bytes) -> str:
        """The payload as ``name=value unit`` pairs, or its hex when it does not decode."""
        if not self.fields:
            return data.hex() or "-"
        try:
            values = self.decode(data)
        except DecodeError:
            return f"{data.hex() or '-'} (does not fit the catalog's layout)"
        units = {f.name: f.unit for f in self.fields}
        return " ".join(
            f"{name}={_show(value)}{' ' + units[name] if units[name] else ''}"
            for name, value in values.items()
        )

    def _need(self) -> str:
        size = self.size
        if size is not None:
            return f"{size}"
        return f"at least {sum(f.size or 0 for f in self.fields)}"


def _raw(f: Field, value: Any) -> int | float | bool:
    """The number a fixed field's value is sent as; strings (from a command line) parsed."""
    if f.type == "bool":
        if isinstance(value, str):
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError("expected true or false")
            return value.lower() in ("true", "1")
        return bool(value)
    if f.type[0] in "iu" and not f.scaled:  # exact: a u64 does not go through a float
        if isinstance(value, str):
            try:
                return int(value, 0)
            except ValueError:
                value = float(value)
        if isinstance(value, float):
            return round(value)
        return int(value)
    number = float(value)
    if f.scaled:
        number = (number - f.offset) / f.scale
    return round(number) if f.type[0] in "iu" else number


def _show(value: Value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, bytes):
        return value.hex() or "-"
    return str(value)


class Catalog:
    """The channels a catalog file describes, by UID. An empty catalog knows nothing."""

    def __init__(self, specs: tuple[ChannelSpec, ...] = (), path: str | None = None) -> None:
        self._by_uid = {s.uid: s for s in specs}
        self.path = path

    def __len__(self) -> int:
        return len(self._by_uid)

    def __iter__(self) -> Iterator[ChannelSpec]:
        return iter(self._by_uid.values())

    def get(self, uid: int) -> ChannelSpec | None:
        return self._by_uid.get(uid)

    def channel(self, uid: int) -> Channel:
        """The channel of ``uid``, named when the catalog knows its name."""
        spec = self._by_uid.get(uid)
        return spec.channel if spec is not None else Channel(uid)

    def format(self, uid: int, data: bytes) -> str:
        """The payload decoded by the catalog when it describes the channel, else its hex."""
        spec = self._by_uid.get(uid)
        return spec.format(data) if spec is not None else data.hex() or "-"

    def decode(self, uid: int, data: bytes) -> dict[str, Value] | None:
        """The payload's fields, or None when the catalog has no layout for the channel or
        the payload does not fit it."""
        spec = self._by_uid.get(uid)
        if spec is None or not spec.fields:
            return None
        try:
            return spec.decode(data)
        except DecodeError:
            return None

    def payload(self, channel: Channel, text: str) -> bytes:
        """A payload as a person writes it: hex digits, or ``field=value,...`` that this
        catalog's layout of ``channel`` encodes (a value cannot hold a comma)."""
        text = text.strip()
        if "=" not in text:
            return hex_bytes(text)
        spec = self._by_uid.get(channel.uid)
        if spec is None or not spec.fields:
            raise ConfigError(f"{text!r}: the catalog has no layout of {channel}")
        values: dict[str, str] = {}
        for pair in text.split(","):
            name, sep, value = pair.partition("=")
            if not sep:
                raise ConfigError(f"{pair!r}: expected field=value")
            if name.strip() in values:
                raise ConfigError(f"{name.strip()} is given twice")
            values[name.strip()] = value.strip()
        return spec.encode(values)

    @classmethod
    def load(cls, path: str | Path) -> Catalog:
        """Read a catalog file; a ConfigError names the file, the channel and what is wrong."""
        from ._tomlfile import read_text

        return cls.from_text(read_text(path, "the catalog"), str(path))

    @classmethod
    def from_text(cls, text: str, source: str = "<text>") -> Catalog:
        """A catalog from TOML text; ``source`` names it in errors."""
        from ._tomlfile import parse_toml

        doc = parse_toml(text, f"catalog {source}")
        unknown = set(doc) - {"channel"}
        if unknown:
            raise ConfigError(f"catalog {source}: unknown table {', '.join(sorted(unknown))}")
        table = doc.get("channel", {})
        if not isinstance(table, dict):
            raise ConfigError(f"catalog {source}: 'channel' must be a table of channels")
        if len(table) > MAX_CHANNELS:
            raise ConfigError(f"catalog {source}: {len(table)} channels, at most {MAX_CHANNELS}")
        specs = []
        for key, entry in table.items():
            try:
                specs.append(_spec(key, entry))
            except UpsError as exc:
                raise ConfigError(f"catalog {source}: channel {key!r}: {exc}") from None
        seen: dict[int, str] = {}
        for s, key in zip(specs, table, strict=True):
            if s.uid in seen:
                raise ConfigError(f"catalog {source}: {key!r} and {seen[s.uid]!r} are one UID")
            seen[s.uid] = key
        return cls(tuple(specs), source)


def _spec(key: str, entry: Any) -> ChannelSpec:
    if not isinstance(entry, dict):
        raise ConfigError("must be a table")
    unknown = set(entry) - _KEYS
    if unknown:
        raise ConfigError(f"unknown key {', '.join(sorted(unknown))}")
    channel = parse_channel(key)
    byte_order = entry.get("byte_order", "little")
    if byte_order not in ("little", "big"):
        raise ConfigError(f"byte_order must be little or big, not {byte_order!r}")
    priority = entry.get("priority")
    if priority is not None and not (isinstance(priority, int) and 2 <= priority <= 255):
        raise ConfigError(
            f"priority must be an integer 2..255 (0, 1: management), not {priority!r}"
        )
    if not isinstance(entry.get("description", ""), str):
        raise ConfigError("description must be a string")
    period = _seconds(entry, "period")
    fields = tuple(_field(i, f) for i, f in enumerate(entry.get("fields", [])))
    names = [f.name for f in fields]
    if len(set(names)) != len(names):
        raise ConfigError("two fields have one name")
    if any(f.size is None for f in fields[:-1]):
        raise ConfigError("only the last field may be str or bytes")
    realtime = None
    if "realtime" in entry:
        rt = entry["realtime"]
        if not isinstance(rt, dict) or set(rt) - {"period", "deadline", "jitter"}:
            raise ConfigError("realtime takes period, deadline and jitter (seconds)")
        rt_period = _seconds(rt, "period") or period
        if rt_period is None:
            raise ConfigError("realtime needs a period (its own or the channel's)")
        realtime = Realtime(rt_period, _seconds(rt, "deadline") or rt_period,
                            _seconds(rt, "jitter", zero=True) or 0.0)  # fmt: skip
    return ChannelSpec(channel, str(entry.get("description", "")), period, priority,
                       byte_order, fields, realtime)  # fmt: skip


def _field(index: int, entry: Any) -> Field:
    if not isinstance(entry, dict):
        raise ConfigError(f"field {index} must be a table {{ name = ..., type = ... }}")
    unknown = set(entry) - _FIELD_KEYS
    if unknown:
        raise ConfigError(f"field {index}: unknown key {', '.join(sorted(unknown))}")
    name, kind = entry.get("name"), entry.get("type")
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(f"field {index}: name must be an identifier, not {name!r}")
    if kind not in FIELD_TYPES:
        raise ConfigError(f"field {name}: type must be one of {' '.join(FIELD_TYPES)}")
    if not isinstance(entry.get("unit", ""), str):
        raise ConfigError(f"field {name}: unit must be a string")
    scale, offset = entry.get("scale", 1.0), entry.get("offset", 0.0)
    for label, value in (("scale", scale), ("offset", offset)):
        if (
            not isinstance(value, int | float)
            or isinstance(value, bool)
            or not math.isfinite(value)
        ):
            raise ConfigError(f"field {name}: {label} must be a finite number")
    if scale == 0:
        raise ConfigError(f"field {name}: scale must not be 0")
    if (scale != 1 or offset != 0) and kind in ("bool", *_TAIL):
        raise ConfigError(f"field {name}: a {kind} field has no scale or offset")
    return Field(name, kind, str(entry.get("unit", "")), float(scale), float(offset))


def _seconds(entry: dict[str, Any], key: str, zero: bool = False) -> float | None:
    value = entry.get(key)
    if value is None:
        return None
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not (value >= 0 if zero else value > 0)
    ):
        least = "0 or more" if zero else "above 0"
        raise ConfigError(f"{key} must be a finite number of seconds {least}, not {value!r}")
    return float(value)


def hex_bytes(text: str) -> bytes:
    """Bytes as a person types them in hex ('' for none, spaces allowed); the error says what
    is wrong: a character that is not a hex digit, or an odd number of digits."""
    try:
        return bytes.fromhex(text)
    except ValueError:
        pass
    digits = "".join(text.split())
    if digits and all(c in "0123456789abcdefABCDEF" for c in digits):
        raise ConfigError(f"{text!r} has an odd number of hex digits ({len(digits)}): a byte is "
                          f"two digits, as in {'0' + digits!r}")  # fmt: skip
    raise ConfigError(f"not hex digits: {text!r}")


def load_catalog(path: str | None) -> Catalog:
    """The catalog at ``path``, else at ``$UPS_CATALOG``, else an empty one."""
    import os

    path = path or os.environ.get("UPS_CATALOG") or None
    return Catalog() if path is None else Catalog.load(path)
