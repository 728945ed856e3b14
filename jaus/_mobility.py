"""Payload codecs of the mobility services the component host offers beyond the Primitive
Driver and the Global Pose Sensor: Local Pose Sensor, Velocity State Sensor, Local Waypoint
Driver, and the Primitive Driver's own report (AS6009 JSIDL, ``urn.jaus.jss.mobility``:
``MessageSet/BasicTypes.xml``, ``CommandClass.xml``, ``QueryClass.xml``, ``InformClass.xml``).
Little-endian, unsigned scaled integers; pure functions. ``docs/jaus.md`` gives the bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import pi
from typing import ClassVar, Self

from ._codec import JausDecodeError, Reader, from_scaled, to_scaled
from ._codes import MessageCode
from ._payloads import (
    SetWrenchEffort,
    TimeStamp,
    _Empty,
    _pack_scaled,
    _presence,
    _Scaled,
    _unpack_scaled,
)

_LOCAL_POSE: tuple[_Scaled, ...] = (
    ("x", 4, -100000.0, 100000.0),
    ("y", 4, -100000.0, 100000.0),
    ("z", 4, -100000.0, 100000.0),
    ("position_rms", 4, 0.0, 100.0),
    ("roll", 2, -pi, pi),
    ("pitch", 2, -pi, pi),
    ("yaw", 2, -pi, pi),
    ("attitude_rms", 2, 0.0, pi),
)
_VELOCITY: tuple[_Scaled, ...] = (
    ("velocity_x", 4, -327.68, 327.67),
    ("velocity_y", 4, -327.68, 327.67),
    ("velocity_z", 4, -327.68, 327.67),
    ("velocity_rms", 4, 0.0, 100.0),
    ("roll_rate", 2, -32.768, 32.767),
    ("pitch_rate", 2, -32.768, 32.767),
    ("yaw_rate", 2, -32.768, 32.767),
    ("rate_rms", 2, 0.0, pi),
)
_WAYPOINT_OPTIONAL: tuple[_Scaled, ...] = (
    ("z", 4, -100000.0, 100000.0),
    ("roll", 2, -pi, pi),
    ("pitch", 2, -pi, pi),
    ("yaw", 2, -pi, pi),
    ("waypoint_tolerance", 2, 0.0, 100.0),
    ("path_tolerance", 4, 0.0, 100000.0),
)
_XY = 100000.0


def _timestamped_to(record: object, layout: tuple[_Scaled, ...]) -> bytes:
    presence, body = _pack_scaled(record, layout)
    stamp = getattr(record, "timestamp")  # noqa: B009
    if stamp is not None:
        presence |= 1 << len(layout)
        body += stamp.to_int().to_bytes(4, "little")
    return presence.to_bytes(2, "little") + body


def _timestamped_from(data: bytes, layout: tuple[_Scaled, ...], what: str) -> dict[str, object]:
    reader = Reader(data, what)
    presence = _presence(reader, len(layout) + 1, what)
    values: dict[str, object] = dict(_unpack_scaled(reader, presence, layout))
    values["timestamp"] = TimeStamp.from_int(reader.u32()) if presence >> len(layout) & 1 else None
    reader.end()
    return values


@dataclass(frozen=True, slots=True)
class _Query16:
    """A query whose body is the presence vector (u16) of the fields wanted."""

    CODE: ClassVar[int]
    presence_vector: int = 0xFFFF

    def to_bytes(self) -> bytes:
        if not 0 <= self.presence_vector <= 0xFFFF:
            raise ValueError("a presence vector is a u16")
        return self.presence_vector.to_bytes(2, "little")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        value = reader.u16()
        reader.end()
        return cls(value)


@dataclass(frozen=True, slots=True)
class QueryLocalPose(_Query16):
    CODE: ClassVar[int] = MessageCode.QUERY_LOCAL_POSE


@dataclass(frozen=True, slots=True)
class QueryVelocityState(_Query16):
    CODE: ClassVar[int] = MessageCode.QUERY_VELOCITY_STATE


@dataclass(frozen=True, slots=True)
class QueryWrenchEffort(_Query16):
    CODE: ClassVar[int] = MessageCode.QUERY_WRENCH_EFFORT


@dataclass(frozen=True, slots=True)
class QueryLocalWaypoint:
    """The presence vector (u8) of the waypoint's optional fields wanted."""

    CODE: ClassVar[int] = MessageCode.QUERY_LOCAL_WAYPOINT
    presence_vector: int = 0xFF

    def to_bytes(self) -> bytes:
        if not 0 <= self.presence_vector <= 0xFF:
            raise ValueError("this presence vector is a u8")
        return bytes((self.presence_vector,))

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "QueryLocalWaypoint")
        value = reader.u8()
        reader.end()
        return cls(value)


@dataclass(frozen=True, slots=True)
class QueryTravelSpeed(_Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_TRAVEL_SPEED


@dataclass(frozen=True, slots=True)
class ReportLocalPose:
    """Position (m, ±100 km) and attitude (rad) in the local frame; None: absent. Presence
    vector u16, bits 0-8; x, y, z, position RMS u32, roll, pitch, yaw, attitude RMS u16, time
    stamp u32."""

    CODE: ClassVar[int] = MessageCode.REPORT_LOCAL_POSE
    x: float | None = None
    y: float | None = None
    z: float | None = None
    position_rms: float | None = None
    roll: float | None = None
    pitch: float | None = None
    yaw: float | None = None
    attitude_rms: float | None = None
    timestamp: TimeStamp | None = None

    def to_bytes(self) -> bytes:
        return _timestamped_to(self, _LOCAL_POSE)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        return cls(**_timestamped_from(data, _LOCAL_POSE, "ReportLocalPose"))  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True)
class ReportVelocityState:
    """Velocities (m/s, -327.68..327.67) and rates (rad/s, -32.768..32.767); None: absent.
    Presence vector u16, bits 0-8; velocities and velocity RMS u32, rates and rate RMS u16, time
    stamp u32."""

    CODE: ClassVar[int] = MessageCode.REPORT_VELOCITY_STATE
    velocity_x: float | None = None
    velocity_y: float | None = None
    velocity_z: float | None = None
    velocity_rms: float | None = None
    roll_rate: float | None = None
    pitch_rate: float | None = None
    yaw_rate: float | None = None
    rate_rms: float | None = None
    timestamp: TimeStamp | None = None

    def to_bytes(self) -> bytes:
        return _timestamped_to(self, _VELOCITY)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        return cls(**_timestamped_from(data, _VELOCITY, "ReportVelocityState"))  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True)
class _Waypoint:
    """Presence vector u8 (bits 0-5: the optional fields), x and y u32 (m, ±100 km, always
    present), then z u32, roll, pitch, yaw u16 (rad), waypoint tolerance u16 (0..100 m), path
    tolerance u32 (0..100 km)."""

    CODE: ClassVar[int]
    PV_FIELDS: ClassVar[tuple[str, ...]] = tuple(f[0] for f in _WAYPOINT_OPTIONAL)
    x: float
    y: float
    z: float | None = None
    roll: float | None = None
    pitch: float | None = None
    yaw: float | None = None
    waypoint_tolerance: float | None = None
    path_tolerance: float | None = None

    def to_bytes(self) -> bytes:
        presence, body = _pack_scaled(self, _WAYPOINT_OPTIONAL)
        xy = b"".join(to_scaled(v, -_XY, _XY, 32).to_bytes(4, "little") for v in (self.x, self.y))
        return bytes((presence,)) + xy + body

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        presence = reader.u8()
        if presence >> len(_WAYPOINT_OPTIONAL):
            raise JausDecodeError(f"{cls.__name__}: presence vector {presence:#04x}")
        x, y = (from_scaled(reader.u32(), -_XY, _XY, 32) for _ in range(2))
        values = _unpack_scaled(reader, presence, _WAYPOINT_OPTIONAL)
        reader.end()
        return cls(x, y, **values)


@dataclass(frozen=True, slots=True)
class SetLocalWaypoint(_Waypoint):
    CODE: ClassVar[int] = MessageCode.SET_LOCAL_WAYPOINT


@dataclass(frozen=True, slots=True)
class ReportLocalWaypoint(_Waypoint):
    CODE: ClassVar[int] = MessageCode.REPORT_LOCAL_WAYPOINT


@dataclass(frozen=True, slots=True)
class _TravelSpeed:
    """Speed u16 scaled 0..327.67 m/s."""

    CODE: ClassVar[int]
    speed: float

    def to_bytes(self) -> bytes:
        return to_scaled(self.speed, 0.0, 327.67, 16).to_bytes(2, "little")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        speed = from_scaled(reader.u16(), 0.0, 327.67, 16)
        reader.end()
        return cls(speed)


@dataclass(frozen=True, slots=True)
class SetTravelSpeed(_TravelSpeed):
    CODE: ClassVar[int] = MessageCode.SET_TRAVEL_SPEED


@dataclass(frozen=True, slots=True)
class ReportTravelSpeed(_TravelSpeed):
    CODE: ClassVar[int] = MessageCode.REPORT_TRAVEL_SPEED


@dataclass(frozen=True, slots=True)
class ReportWrenchEffort(SetWrenchEffort):
    """The efforts in force: Set Wrench Effort's record."""

    CODE: ClassVar[int] = MessageCode.REPORT_WRENCH_EFFORT


TYPES: tuple[type, ...] = (
    QueryLocalPose, ReportLocalPose, QueryVelocityState, ReportVelocityState,
    QueryWrenchEffort, ReportWrenchEffort, SetLocalWaypoint, QueryLocalWaypoint,
    ReportLocalWaypoint, SetTravelSpeed, QueryTravelSpeed, ReportTravelSpeed,
)  # fmt: skip
