"""RA 3.3 message data as the same payload objects the AS5710A/AS6009 codecs give, for the
messages the component host serves (paper 001's framing; layouts from OpenJAUS 3.3.1,
``libjaus/src/message/*``). Most share code and bytes with AS5710A; these differ:

- Reject Component Control (0x0010) has no data (AS5710A: a response code). Decoded as
  ``RejectControl(CONTROL_RELEASED)``; encoded empty, whatever the response.
- Report Component Control (0x400D): subsystem, node, component, instance, authority, a byte
  each (AS5710A: subsystem u16, no instance).
- Report Identification (0x4B00): query type u8, authority u8, type u16, then the
  identification to the end of the data (AS5710A: no authority, a count byte before the text).
- Set Wrench Effort (0x0405) and Report Global Pose (0x4402): the same fields and presence
  vectors, but signed scaled integers where AS6009 has unsigned ones (propulsive efforts i16,
  latitude, longitude, elevation i32, roll, pitch, yaw i16): ``jausShortFromDouble`` is
  round((value - (max + min) / 2) / ((max - min) / 65534)).

Codes not served here give None. Pure functions; bad bytes raise only JausDecodeError.
"""

from __future__ import annotations

from collections.abc import Callable
from math import pi
from typing import Any

from ._codec import JausDecodeError, Reader, from_scaled, to_scaled
from ._codes import MessageCode, message_name
from ._messages import PAYLOAD_TYPES
from ._payloads import (
    RejectControl,
    RejectResponse,
    ReportControl,
    ReportGlobalPose,
    ReportIdentification,
    SetWrenchEffort,
    TimeStamp,
)

# (field, bytes, lower, upper, signed) in presence-vector order
_WRENCH = (
    *(
        (f"propulsive_{axis}", 2, -100.0, 100.0, True)
        for axis in (
            "linear_x",
            "linear_y",
            "linear_z",
            "rotational_x",
            "rotational_y",
            "rotational_z",
        )
    ),
    *(
        (f"resistive_{axis}", 1, 0.0, 100.0, False)
        for axis in (
            "linear_x",
            "linear_y",
            "linear_z",
            "rotational_x",
            "rotational_y",
            "rotational_z",
        )
    ),
)
_POSE = (
    ("latitude", 4, -90.0, 90.0, True),
    ("longitude", 4, -180.0, 180.0, True),
    ("altitude", 4, -10000.0, 35000.0, True),
    ("position_rms", 4, 0.0, 100.0, False),
    ("roll", 2, -pi, pi, True),
    ("pitch", 2, -pi, pi, True),
    ("yaw", 2, -pi, pi, True),
    ("attitude_rms", 2, 0.0, pi, False),
)
_Layout = tuple[tuple[str, int, float, float, bool], ...]


def _pack(record: Any, layout: _Layout) -> tuple[int, bytes]:
    presence, out = 0, bytearray()
    for bit, (name, size, lower, upper, signed) in enumerate(layout):
        value = getattr(record, name)
        if value is not None:
            presence |= 1 << bit
            raw = to_scaled(value, lower, upper, 8 * size, signed=signed)
            out += raw.to_bytes(size, "little", signed=signed)
    return presence, bytes(out)


def _unpack(reader: Reader, presence: int, layout: _Layout) -> dict[str, float | None]:
    values: dict[str, float | None] = {}
    for bit, (name, size, lower, upper, signed) in enumerate(layout):
        if presence >> bit & 1:
            raw = int.from_bytes(reader.take(size), "little", signed=signed)
            values[name] = from_scaled(raw, lower, upper, 8 * size, signed=signed)
        else:
            values[name] = None
    return values


def _presence(reader: Reader, defined: int, what: str) -> int:
    presence = reader.u16()
    if presence >> defined:
        raise JausDecodeError(f"{what}: presence vector {presence:#06x} has undefined bits")
    return presence


def _wrench_from(data: bytes) -> SetWrenchEffort:
    reader = Reader(data, "RA 3.3 SetWrenchEffort")
    values = _unpack(reader, _presence(reader, len(_WRENCH), "SetWrenchEffort"), _WRENCH)
    reader.end()
    return SetWrenchEffort(**values)


def _wrench_to(msg: SetWrenchEffort) -> bytes:
    presence, body = _pack(msg, _WRENCH)
    return presence.to_bytes(2, "little") + body


def _pose_from(data: bytes) -> ReportGlobalPose:
    reader = Reader(data, "RA 3.3 ReportGlobalPose")
    presence = _presence(reader, len(_POSE) + 1, "ReportGlobalPose")
    values = _unpack(reader, presence, _POSE)
    stamp = TimeStamp.from_int(reader.u32()) if presence >> len(_POSE) & 1 else None
    reader.end()
    return ReportGlobalPose(**values, timestamp=stamp)


def _pose_to(msg: ReportGlobalPose) -> bytes:
    presence, body = _pack(msg, _POSE)
    if msg.timestamp is not None:
        presence |= 1 << len(_POSE)
        body += msg.timestamp.to_int().to_bytes(4, "little")
    return presence.to_bytes(2, "little") + body


def _control_from(data: bytes) -> ReportControl:
    reader = Reader(data, "RA 3.3 ReportComponentControl")
    subsystem, node, component, _instance, authority = (reader.u8() for _ in range(5))
    reader.end()
    return ReportControl(subsystem, node, component, authority)


def _control_to(msg: ReportControl) -> bytes:
    if msg.subsystem > 0xFF:
        raise ValueError("an RA 3.3 subsystem id is a byte")
    instance = 1 if msg.component else 0
    return bytes((msg.subsystem, msg.node, msg.component, instance, msg.authority))


def _reject_from(data: bytes) -> RejectControl:
    Reader(data, "RA 3.3 RejectComponentControl").end()
    return RejectControl(RejectResponse.CONTROL_RELEASED)


def _identification_from(data: bytes) -> ReportIdentification:
    reader = Reader(data, "RA 3.3 ReportIdentification")
    query_type, _authority, kind = reader.u8(), reader.u8(), reader.u16()
    text = reader.take(reader.remaining).rstrip(b"\0").decode("utf-8", "replace")
    return ReportIdentification(query_type, kind, text)


def _identification_to(msg: ReportIdentification) -> bytes:
    return (
        bytes((int(msg.query_type), 0))
        + int(msg.identification_type).to_bytes(2, "little")
        + msg.identification.encode()
    )


#: code -> (decode, encode) where RA 3.3 differs from AS5710A/AS6009
RA33_TYPES: dict[int, tuple[Callable[[bytes], Any], Callable[[Any], bytes]]] = {
    MessageCode.REJECT_CONTROL: (_reject_from, lambda msg: b""),
    MessageCode.REPORT_CONTROL: (_control_from, _control_to),
    MessageCode.REPORT_IDENTIFICATION: (_identification_from, _identification_to),
    MessageCode.SET_WRENCH_EFFORT: (_wrench_from, _wrench_to),
    MessageCode.REPORT_GLOBAL_POSE: (_pose_from, _pose_to),
}
#: codes served in RA 3.3 with AS5710A's layout (OpenJAUS 3.3.1 writes the same bytes)
SAME = frozenset(
    {
        MessageCode.SET_AUTHORITY,
        MessageCode.SHUTDOWN,
        MessageCode.STANDBY,
        MessageCode.RESUME,
        MessageCode.RESET,
        MessageCode.SET_EMERGENCY,
        MessageCode.CLEAR_EMERGENCY,
        MessageCode.REQUEST_CONTROL,
        MessageCode.RELEASE_CONTROL,
        MessageCode.CONFIRM_CONTROL,
        MessageCode.QUERY_AUTHORITY,
        MessageCode.QUERY_STATUS,
        MessageCode.QUERY_CONTROL,
        MessageCode.QUERY_HEARTBEAT_PULSE,
        MessageCode.QUERY_IDENTIFICATION,
        MessageCode.QUERY_GLOBAL_POSE,
        MessageCode.REPORT_AUTHORITY,
        MessageCode.REPORT_STATUS,
        MessageCode.REPORT_HEARTBEAT_PULSE,
    }
)


def decode_ra33_payload(code: int, data: bytes) -> Any | None:
    """RA 3.3 message data as a payload object, None for codes not served in RA 3.3."""
    if code in RA33_TYPES:
        return RA33_TYPES[code][0](data)
    if code in SAME:
        return PAYLOAD_TYPES[code].from_bytes(data)  # type: ignore[attr-defined]
    return None


def encode_ra33_payload(payload: Any) -> tuple[int, bytes]:
    """(command code, RA 3.3 data) of ``payload``; ValueError for what RA 3.3 cannot carry."""
    code = payload.CODE
    if code in RA33_TYPES:
        return code, RA33_TYPES[code][1](payload)
    if code in SAME:
        return code, payload.to_bytes()
    name = message_name(code) or f"message {code:#06x}"
    raise ValueError(f"{name} is not served in the RA 3.3 framing")


__all__ = ["RA33_TYPES", "decode_ra33_payload", "encode_ra33_payload"]
