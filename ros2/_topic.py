"""One topic of a map, compiled: the channel's payload as a ``struct.Struct``, the message as a
``Codec``, and per mapped field a converter closure made once. Converting an event is then an
unpack, a few multiplications and a pack.

A value the other side cannot hold is never clipped: an integer out of its type's range, NaN
or an infinity into an integer, a float32 beyond its range, anything but 0 or 1 into a bool
raises ``Unrepresentable``, and the bridge drops the event and counts it. Floats into integers
round to the nearest (the catalog's scale fixes the precision); nothing else is rounded.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ups import ConfigError, DecodeError, UpsError
from ups._catalog import ChannelSpec

from ._admit import DEFAULT_BURST, DEFAULT_RATE
from ._cdr import Codec
from ._rmw import Qos, topic_key
from ._types import PRIMITIVES, STRING, Item, Value

#: catalog field types: struct code
_CODES = {
    "u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i",
    "u64": "Q", "i64": "q", "f32": "f", "f64": "d", "bool": "?",
}  # fmt: skip
NUMERIC = frozenset(_CODES)
_FLOAT32_MAX = 3.4028234663852886e38


class Unrepresentable(UpsError):
    """A value the receiving side's type cannot hold: the event is dropped and counted."""


@dataclass(frozen=True, slots=True)
class FieldMap:
    """``catalog value = ros * scale + offset``, and back."""

    ros: str
    ups: str
    scale: float = 1.0
    offset: float = 0.0


def _limits(code: str) -> tuple[int, int] | None:
    if code in "fd?":
        return None
    bits = struct.calcsize(code) * 8
    return (0, (1 << bits) - 1) if code.isupper() else (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)


def converter(code: str, where: str) -> Callable[[Any], Any]:
    """A function that makes a value fit struct code ``code`` exactly, or raises."""
    limits = _limits(code)
    if limits is not None:
        low, high = limits

        def to_int(value: Any) -> int:
            if not isinstance(value, int):
                if not math.isfinite(value):
                    raise Unrepresentable(f"{where}: {value} is not an integer")
                value = round(value)
            if not low <= value <= high:
                raise Unrepresentable(f"{where}: {value} is out of range {low}..{high}")
            return int(value)

        return to_int
    if code == "?":

        def to_bool(value: Any) -> bool:
            if value not in (0, 1):
                raise Unrepresentable(f"{where}: {value} is not a bool (0 or 1)")
            return bool(value)

        return to_bool
    if code == "f":

        def to_float32(value: Any) -> float:
            number = float(value)
            if math.isfinite(number) and abs(number) > _FLOAT32_MAX:
                raise Unrepresentable(f"{where}: {number} is out of float32's range")
            return number

        return to_float32
    return float


def _linear(scale: float, offset: float, fit: Callable[[Any], Any]) -> Callable[[Any], Any]:
    if scale == 1.0 and offset == 0.0:
        return fit  # an integer stays exact (a u64 never goes through a float)
    return lambda value: fit(value * scale + offset)


@dataclass(slots=True)
class TopicMap:
    """A topic of the map, ready to convert events both ways."""

    topic: str
    channel: ChannelSpec
    type: str
    type_hash: str
    direction: str
    qos: Qos
    key: str  #: rmw_zenoh's data key expression
    fields: tuple[FieldMap, ...]
    line: int
    codec: Codec
    _unpack: Callable[[bytes], tuple[Any, ...]] = field(repr=False)
    _pack: Callable[[list[Any]], bytes] = field(repr=False)
    _template: list[Any] = field(repr=False)
    _to_ros: list[tuple[int, int, Callable[[Any], Any]]] = field(repr=False)
    _to_ups: list[tuple[int, int | None, Any]] = field(repr=False)
    _stamp: tuple[int, int] | None = field(repr=False)
    max_rate: float = DEFAULT_RATE  #: samples a second taken from ROS (``_admit``)
    burst: int = DEFAULT_BURST  #: samples taken back to back after a silence

    @property
    def to_ros(self) -> bool:
        return self.direction in ("to_ros", "both")

    @property
    def from_ros(self) -> bool:
        return self.direction in ("from_ros", "both")

    def ros_payload(self, data: bytes, when: float) -> bytes:
        """The CDR message of the channel's event ``data`` (arrived at ``when``, seconds since
        the epoch); ``DecodeError`` when ``data`` does not fit the catalog's layout,
        ``Unrepresentable`` when a value does not fit its ROS field."""
        raw = self._unpack(data)
        values = list(self._template)
        for slot, index, convert in self._to_ros:
            values[slot] = convert(raw[index])
        if self._stamp is not None:  # (when * 1e9 would lose the last bits of a float)
            sec = math.floor(when)
            nanosec = min(round((when - sec) * 1e9), 999_999_999)
            values[self._stamp[0]], values[self._stamp[1]] = sec, nanosec
        try:
            return self.codec.encode(values)
        except (struct.error, OverflowError) as exc:  # a constant's own range was checked
            raise Unrepresentable(f"{self.topic}: {exc}") from None

    def ups_payload(self, message: bytes) -> bytes:
        """The channel's event of the CDR ``message``; ``DecodeError`` (``CdrError``) or
        ``Unrepresentable`` when it cannot be made."""
        values = self.codec.decode(message)
        raw = [
            convert(values[slot]) if slot is not None else convert
            for _, slot, convert in self._to_ups
        ]
        return self._pack(raw)

    def describe(self) -> dict[str, Any]:
        """What ``ups status`` and ``ups ros2 check`` show of it."""
        return {
            "topic": self.topic,
            "channel": str(self.channel.channel),
            "uid": f"0x{self.channel.uid:016x}",
            "type": self.type,
            "direction": self.direction,
            "key": self.key,
            "qos": self.qos.chunk(),
            "fields": {f.ros: f.ups for f in self.fields},
            **({"max_rate": self.max_rate, "burst": self.burst} if self.from_ros else {}),
        }


def build_topic(
    topic: str,
    spec: ChannelSpec,
    type_name: str,
    type_hash: str,
    direction: str,
    qos: Qos,
    items: tuple[Item, ...],
    maps: tuple[FieldMap, ...],
    constants: Mapping[str, Any],
    ups_constants: Mapping[str, Any],
    stamp: str | None,
    domain: int,
    line: int,
    max_rate: float = DEFAULT_RATE,
    burst: int = DEFAULT_BURST,
) -> TopicMap:
    """Compile a checked topic (``_mapping`` checked names, types and bounds)."""
    codec = Codec(items)
    slots = {v.path: i for i, v in enumerate(codec.values)}
    kinds = {v.path: v for v in codec.values}
    unpack, pack = _payload(spec)
    ups_fields = list(spec.fields)
    index = {f.name: i for i, f in enumerate(ups_fields)}

    template = codec.zeros()
    for path, value in constants.items():
        template[slots[path]] = _constant(kinds[path], value, f"constant {path}")

    to_ros: list[tuple[int, int, Callable[[Any], Any]]] = []
    for m in maps:
        f, value = ups_fields[index[m.ups]], kinds[m.ros]
        if value.type == STRING:
            to_ros.append((slots[m.ros], index[m.ups], str))
            continue
        # ros = (raw * field scale + field offset - offset) / scale
        fit = converter(PRIMITIVES[value.type], f"{topic} {m.ros}")
        convert = _linear(f.scale / m.scale, (f.offset - m.offset) / m.scale, fit)
        to_ros.append((slots[m.ros], index[m.ups], convert))

    to_ups: list[tuple[int, int | None, Any]] = []
    by_ups = {m.ups: m for m in maps}
    for f in ups_fields:
        if f.type in ("str", "bytes"):
            if f.name in by_ups:
                to_ups.append((index[f.name], slots[by_ups[f.name].ros], _tail(f.type)))
            else:
                to_ups.append((index[f.name], None, _tail(f.type)(ups_constants.get(f.name, ""))))
            continue
        fit = converter(_CODES[f.type], f"{spec.channel} {f.name}")
        found = by_ups.get(f.name)
        if found is not None:  # raw = (ros * scale + offset - field offset) / field scale
            convert = _linear(found.scale / f.scale, (found.offset - f.offset) / f.scale, fit)
            to_ups.append((index[f.name], slots[found.ros], convert))
        elif f.name in ups_constants:
            value = ups_constants[f.name]
            raw = (value - f.offset) / f.scale if f.scaled else value
            try:
                to_ups.append((index[f.name], None, fit(raw)))
            except Unrepresentable as exc:
                raise ConfigError(f"ups_constants: {exc}") from None
        else:  # a channel only sent to ROS: no value needed
            to_ups.append((index[f.name], None, fit(0)))
    time_slots = None
    if stamp is not None:
        time_slots = (slots[f"{stamp}.sec"], slots[f"{stamp}.nanosec"])
    key = topic_key(domain, topic, type_name, type_hash)
    return TopicMap(
        topic, spec, type_name, type_hash, direction, qos, key, maps, line, codec, unpack, pack,
        template, to_ros, to_ups, time_slots, max_rate, burst,
    )  # fmt: skip


def _tail(kind: str) -> Callable[[Any], Any]:
    if kind == "bytes":
        return lambda text: str(text).encode("utf-8")
    return str


def _constant(value: Value, given: Any, where: str) -> Any:
    if value.type == STRING:
        return str(given)
    try:
        return converter(PRIMITIVES[value.type], where)(given)
    except Unrepresentable as exc:
        raise ConfigError(str(exc)) from None


def _payload(
    spec: ChannelSpec,
) -> tuple[Callable[[bytes], tuple[Any, ...]], Callable[[list[Any]], bytes]]:
    """The channel's payload as a struct: unpack (values in field order; the last ``str`` or
    ``bytes`` field is the rest of the payload) and pack."""
    order = "<" if spec.byte_order == "little" else ">"
    fixed = [f for f in spec.fields if f.type in _CODES]
    layout = struct.Struct(order + "".join(_CODES[f.type] for f in fixed))
    size = layout.size
    tail = spec.fields[-1].type if spec.fields[-1].type not in _CODES else None
    name = spec.channel

    if tail is None:

        def unpack(data: bytes) -> tuple[Any, ...]:
            if len(data) != size:
                raise DecodeError(f"{name}: {len(data)} bytes, the layout needs {size}")
            return layout.unpack(data)

        def pack(values: list[Any]) -> bytes:
            return layout.pack(*values)

        return unpack, pack

    def unpack_tail(data: bytes) -> tuple[Any, ...]:
        if len(data) < size:
            raise DecodeError(f"{name}: {len(data)} bytes, the layout needs at least {size}")
        rest = data[size:]
        if tail == "str":
            try:
                return (*layout.unpack_from(data), rest.decode("utf-8"))
            except UnicodeDecodeError:
                raise DecodeError(f"{name}: its text is not UTF-8") from None
        return (*layout.unpack_from(data), rest.decode("utf-8", "replace"))

    def pack_tail(values: list[Any]) -> bytes:
        last = values[-1]
        return layout.pack(*values[:-1]) + (last if isinstance(last, bytes) else
                                            str(last).encode("utf-8"))  # fmt: skip

    return unpack_tail, pack_tail
