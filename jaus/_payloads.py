"""Payload codecs for a few core and mobility messages (the bytes after the message code).

Layouts are the JSIDL records of AS5710A (core 1.1) and AS6009 (mobility); every field is
little-endian. ``docs/jaus.md`` ("Payloads") gives the bytes and the sources. Pure functions.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from enum import IntEnum
from math import pi
from typing import ClassVar, Self, TypeVar

from ._codec import JausDecodeError, Reader, from_scaled, to_scaled
from ._codes import MessageCode


class ControlResponse(IntEnum):
    """Confirm Control's response code."""

    CONTROL_ACCEPTED = 0
    NOT_AVAILABLE = 1
    INSUFFICIENT_AUTHORITY = 2


class RejectResponse(IntEnum):
    """Reject Control's response code."""

    CONTROL_RELEASED = 0
    NOT_AVAILABLE = 1


class QueryType(IntEnum):
    """What Query/Report Identification is about (0 and 5-255 are reserved, yet carried)."""

    SYSTEM = 1
    SUBSYSTEM = 2
    NODE = 3
    COMPONENT = 4


class IdentificationType(IntEnum):
    """Report Identification's type (other values are reserved, yet carried)."""

    VEHICLE = 10001
    OCU = 20001
    OTHER_SUBSYSTEM = 30001
    NODE = 40001
    PAYLOAD = 50001
    COMPONENT = 60001


_E = TypeVar("_E", bound=IntEnum)


def _enum(kind: type[_E], value: int, what: str) -> _E:
    try:
        return kind(value)
    except ValueError:
        raise JausDecodeError(f"{what}: undefined value {value}") from None


def _byte(value: int, what: str) -> bytes:
    if not 0 <= value <= 0xFF:
        raise ValueError(f"{what} is a byte, not {value}")
    return bytes((value,))


@dataclass(frozen=True, slots=True)
class _Empty:
    """A message whose body is empty."""

    CODE: ClassVar[int]

    def to_bytes(self) -> bytes:
        return b""

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        Reader(data, cls.__name__).end()
        return cls()


@dataclass(frozen=True, slots=True)
class ReleaseControl(_Empty):
    CODE: ClassVar[int] = MessageCode.RELEASE_CONTROL


@dataclass(frozen=True, slots=True)
class QueryControl(_Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_CONTROL


@dataclass(frozen=True, slots=True)
class QueryAuthority(_Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_AUTHORITY


@dataclass(frozen=True, slots=True)
class QueryHeartbeatPulse(_Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_HEARTBEAT_PULSE


@dataclass(frozen=True, slots=True)
class ReportHeartbeatPulse(_Empty):
    CODE: ClassVar[int] = MessageCode.REPORT_HEARTBEAT_PULSE


@dataclass(frozen=True, slots=True)
class _Authority:
    """A message whose body is one authority code (u8, 0-255, 255 highest)."""

    CODE: ClassVar[int]
    authority: int

    def to_bytes(self) -> bytes:
        return _byte(self.authority, "an authority code")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        authority = reader.u8()
        reader.end()
        return cls(authority)


@dataclass(frozen=True, slots=True)
class RequestControl(_Authority):
    CODE: ClassVar[int] = MessageCode.REQUEST_CONTROL


@dataclass(frozen=True, slots=True)
class SetAuthority(_Authority):
    CODE: ClassVar[int] = MessageCode.SET_AUTHORITY


@dataclass(frozen=True, slots=True)
class ReportAuthority(_Authority):
    CODE: ClassVar[int] = MessageCode.REPORT_AUTHORITY


@dataclass(frozen=True, slots=True)
class ConfirmControl:
    CODE: ClassVar[int] = MessageCode.CONFIRM_CONTROL
    response: ControlResponse

    def to_bytes(self) -> bytes:
        return bytes((ControlResponse(self.response),))

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ConfirmControl")
        response = _enum(ControlResponse, reader.u8(), "ConfirmControl response code")
        reader.end()
        return cls(response)


@dataclass(frozen=True, slots=True)
class RejectControl:
    CODE: ClassVar[int] = MessageCode.REJECT_CONTROL
    response: RejectResponse

    def to_bytes(self) -> bytes:
        return bytes((RejectResponse(self.response),))

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "RejectControl")
        response = _enum(RejectResponse, reader.u8(), "RejectControl response code")
        reader.end()
        return cls(response)


@dataclass(frozen=True, slots=True)
class ReportControl:
    """Who controls the service (all zero: nobody), and with which authority."""

    CODE: ClassVar[int] = MessageCode.REPORT_CONTROL
    subsystem: int
    node: int
    component: int
    authority: int

    def to_bytes(self) -> bytes:
        if not 0 <= self.subsystem <= 0xFFFF:
            raise ValueError(f"a subsystem id is a u16, not {self.subsystem}")
        return (
            self.subsystem.to_bytes(2, "little")
            + _byte(self.node, "a node id")
            + _byte(self.component, "a component id")
            + _byte(self.authority, "an authority code")
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportControl")
        result = cls(reader.u16(), reader.u8(), reader.u8(), reader.u8())
        reader.end()
        return result


@dataclass(frozen=True, slots=True)
class QueryIdentification:
    CODE: ClassVar[int] = MessageCode.QUERY_IDENTIFICATION
    query_type: int = QueryType.COMPONENT

    def to_bytes(self) -> bytes:
        return _byte(self.query_type, "a query type")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "QueryIdentification")
        query_type = reader.u8()
        reader.end()
        return cls(query_type)


@dataclass(frozen=True, slots=True)
class ReportIdentification:
    """``identification``: a human-readable name of at most 255 UTF-8 bytes."""

    CODE: ClassVar[int] = MessageCode.REPORT_IDENTIFICATION
    query_type: int
    identification_type: int
    identification: str

    def to_bytes(self) -> bytes:
        name = self.identification.encode()
        if len(name) > 0xFF:
            raise ValueError("an identification is at most 255 bytes")
        if not 0 <= self.identification_type <= 0xFFFF:
            raise ValueError(f"the identification type is a u16: {self.identification_type}")
        return (
            _byte(self.query_type, "a query type")
            + self.identification_type.to_bytes(2, "little")
            + bytes((len(name),))
            + name
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportIdentification")
        query_type, kind = reader.u8(), reader.u16()
        name = reader.take(reader.u8()).decode("utf-8", "replace")
        reader.end()
        return cls(query_type, kind, name)


@dataclass(frozen=True, slots=True)
class TimeStamp:
    """JSIDL's TimeStamp bit field (u32): ms bits 0-9, s 10-15, min 16-21, h 22-26, day 27-31."""

    day: int
    hour: int
    minute: int
    second: int
    millisecond: int

    def __post_init__(self) -> None:
        if not (1 <= self.day <= 31 and 0 <= self.hour <= 23 and 0 <= self.minute <= 59
                and 0 <= self.second <= 59 and 0 <= self.millisecond <= 999):  # fmt: skip
            raise ValueError(f"not a JAUS time stamp: {self}")

    def to_int(self) -> int:
        return (
            self.millisecond | self.second << 10 | self.minute << 16 | self.hour << 22
            | self.day << 27
        )  # fmt: skip

    @classmethod
    def at(cls, epoch: float) -> TimeStamp:
        """The time stamp of ``epoch`` (seconds since 1970), in UTC."""
        t = datetime.fromtimestamp(epoch, UTC)
        return cls(t.day, t.hour, t.minute, t.second, t.microsecond // 1000)

    @classmethod
    def from_int(cls, value: int) -> TimeStamp:
        try:
            return cls(
                day=value >> 27,
                hour=(value >> 22) & 0x1F,
                minute=(value >> 16) & 0x3F,
                second=(value >> 10) & 0x3F,
                millisecond=value & 0x3FF,
            )
        except ValueError as error:
            raise JausDecodeError(str(error)) from None


# (field name, bytes, lower, upper) of the scaled fields of a presence-vector record, in order
_Scaled = tuple[str, int, float, float]

_WRENCH: tuple[_Scaled, ...] = (
    *((f"propulsive_{axis}", 2, -100.0, 100.0) for axis in (
        "linear_x", "linear_y", "linear_z", "rotational_x", "rotational_y", "rotational_z")),
    *((f"resistive_{axis}", 1, 0.0, 100.0) for axis in (
        "linear_x", "linear_y", "linear_z", "rotational_x", "rotational_y", "rotational_z")),
)  # fmt: skip

_POSE: tuple[_Scaled, ...] = (
    ("latitude", 4, -90.0, 90.0),
    ("longitude", 4, -180.0, 180.0),
    ("altitude", 4, -10000.0, 35000.0),
    ("position_rms", 4, 0.0, 100.0),
    ("roll", 2, -pi, pi),
    ("pitch", 2, -pi, pi),
    ("yaw", 2, -pi, pi),
    ("attitude_rms", 2, 0.0, pi),
)


def _pack_scaled(record: object, layout: tuple[_Scaled, ...]) -> tuple[int, bytes]:
    presence, out = 0, bytearray()
    for bit, (name, size, lower, upper) in enumerate(layout):
        value = getattr(record, name)
        if value is not None:
            presence |= 1 << bit
            out += to_scaled(value, lower, upper, 8 * size).to_bytes(size, "little")
    return presence, bytes(out)


def _unpack_scaled(
    reader: Reader, presence: int, layout: tuple[_Scaled, ...]
) -> dict[str, float | None]:
    values: dict[str, float | None] = {}
    for bit, (name, size, lower, upper) in enumerate(layout):
        if presence >> bit & 1:
            raw = int.from_bytes(reader.take(size), "little")
            values[name] = from_scaled(raw, lower, upper, 8 * size)
        else:
            values[name] = None
    return values


def _presence(reader: Reader, defined: int, what: str) -> int:
    presence = reader.u16()
    if presence >> defined:
        raise JausDecodeError(f"{what}: presence vector {presence:#06x} has undefined bits")
    return presence


@dataclass(frozen=True, slots=True)
class SetWrenchEffort:
    """Open-loop effort in percent: propulsive -100..100 (u16 scaled), resistive 0..100 (u8
    scaled). None: the field is absent (its presence-vector bit is 0)."""

    CODE: ClassVar[int] = MessageCode.SET_WRENCH_EFFORT
    propulsive_linear_x: float | None = None
    propulsive_linear_y: float | None = None
    propulsive_linear_z: float | None = None
    propulsive_rotational_x: float | None = None
    propulsive_rotational_y: float | None = None
    propulsive_rotational_z: float | None = None
    resistive_linear_x: float | None = None
    resistive_linear_y: float | None = None
    resistive_linear_z: float | None = None
    resistive_rotational_x: float | None = None
    resistive_rotational_y: float | None = None
    resistive_rotational_z: float | None = None

    def to_bytes(self) -> bytes:
        presence, body = _pack_scaled(self, _WRENCH)
        return presence.to_bytes(2, "little") + body

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "SetWrenchEffort")
        presence = _presence(reader, len(_WRENCH), "SetWrenchEffort")
        values = _unpack_scaled(reader, presence, _WRENCH)
        reader.end()
        return cls(**values)


@dataclass(frozen=True, slots=True)
class QueryGlobalPose:
    """Which fields of Report Global Pose are wanted (any u16: the responder ANDs it with the
    fields it has)."""

    CODE: ClassVar[int] = MessageCode.QUERY_GLOBAL_POSE
    presence_vector: int = 0x01FF

    def to_bytes(self) -> bytes:
        if not 0 <= self.presence_vector <= 0xFFFF:
            raise ValueError("a presence vector is a u16")
        return self.presence_vector.to_bytes(2, "little")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "QueryGlobalPose")
        presence = reader.u16()
        reader.end()
        return cls(presence)


@dataclass(frozen=True, slots=True)
class ReportGlobalPose:
    """WGS 84 position (degrees, metres) and attitude (radians); None: absent."""

    CODE: ClassVar[int] = MessageCode.REPORT_GLOBAL_POSE
    latitude: float | None = None
    longitude: float | None = None
    altitude: float | None = None
    position_rms: float | None = None
    roll: float | None = None
    pitch: float | None = None
    yaw: float | None = None
    attitude_rms: float | None = None
    timestamp: TimeStamp | None = None

    def to_bytes(self) -> bytes:
        presence, body = _pack_scaled(self, _POSE)
        if self.timestamp is not None:
            presence |= 1 << len(_POSE)
            body += self.timestamp.to_int().to_bytes(4, "little")
        return presence.to_bytes(2, "little") + body

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportGlobalPose")
        presence = _presence(reader, len(_POSE) + 1, "ReportGlobalPose")
        values = _unpack_scaled(reader, presence, _POSE)
        timestamp = TimeStamp.from_int(reader.u32()) if presence >> len(_POSE) & 1 else None
        reader.end()
        return cls(**values, timestamp=timestamp)


Payload = (
    ReleaseControl | QueryControl | QueryAuthority | QueryHeartbeatPulse | ReportHeartbeatPulse
    | RequestControl | SetAuthority | ReportAuthority | ConfirmControl | RejectControl
    | ReportControl | QueryIdentification | ReportIdentification | SetWrenchEffort
    | QueryGlobalPose | ReportGlobalPose
)  # fmt: skip

TYPES: tuple[type[Payload], ...] = (
    ReleaseControl, QueryControl, QueryAuthority, QueryHeartbeatPulse, ReportHeartbeatPulse,
    RequestControl, SetAuthority, ReportAuthority, ConfirmControl, RejectControl,
    ReportControl, QueryIdentification, ReportIdentification, SetWrenchEffort,
    QueryGlobalPose, ReportGlobalPose,
)  # fmt: skip
