"""Payload codecs of the Events service (AS5710A core 1.1 JSIDL: ``CommandClass.xml``,
``InformClass.xml``, ``BasicTypes.xml``): creating, updating and cancelling an event, its
confirmation or rejection, and the Event that carries a report. Little-endian; pure functions.
``docs/jaus.md`` ("Payloads") gives the bytes and the sources.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar, Self

from ._codec import JausDecodeError, Reader, from_scaled, to_scaled
from ._codes import MessageCode
from ._payloads import _byte, _enum

MAX_EVENT_RATE = 1092.0  #: Hz: the upper end of Create Event's scaled periodic rate


class EventType(IntEnum):
    PERIODIC = 0
    EVERY_CHANGE = 1


class EventRejection(IntEnum):
    """Reject Event Request's response code."""

    PERIODIC_UNSUPPORTED = 1
    CHANGE_UNSUPPORTED = 2
    CONNECTION_REFUSED = 3
    INVALID_SETUP = 4
    MESSAGE_UNSUPPORTED = 5
    INVALID_EVENT_ID = 6


def _rate(value: float) -> bytes:
    return to_scaled(value, 0.0, MAX_EVENT_RATE, 16).to_bytes(2, "little")


def _message(reader: Reader, what: str) -> bytes:
    """A whole JAUS message: count u32, then that many bytes (its code and payload)."""
    count = reader.u32()
    if count < 2:
        raise JausDecodeError(f"{what}: a message of {count} bytes has no code")
    return reader.take(count)


def _pack_message(message: bytes) -> bytes:
    if len(message) < 2:
        raise ValueError("a JAUS message starts with its 2-byte code")
    return len(message).to_bytes(4, "little") + message


@dataclass(frozen=True, slots=True)
class CreateEvent:
    """Request id u8, event type u8, requested periodic rate u16 scaled 0..1092 Hz, the query
    message: count u32 + the message (code u16 and payload)."""

    CODE: ClassVar[int] = MessageCode.CREATE_EVENT
    request_id: int
    event_type: EventType
    requested_periodic_rate: float
    query_message: bytes

    def to_bytes(self) -> bytes:
        return (
            _byte(self.request_id, "a request id")
            + bytes((EventType(self.event_type),))
            + _rate(self.requested_periodic_rate)
            + _pack_message(self.query_message)
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "CreateEvent")
        request_id = reader.u8()
        kind = _enum(EventType, reader.u8(), "CreateEvent event type")
        rate = from_scaled(reader.u16(), 0.0, MAX_EVENT_RATE, 16)
        query = _message(reader, "CreateEvent")
        reader.end()
        return cls(request_id, kind, rate, query)


@dataclass(frozen=True, slots=True)
class UpdateEvent:
    """As Create Event, with the event id before the query message."""

    CODE: ClassVar[int] = MessageCode.UPDATE_EVENT
    request_id: int
    event_type: EventType
    requested_periodic_rate: float
    event_id: int
    query_message: bytes

    def to_bytes(self) -> bytes:
        return (
            _byte(self.request_id, "a request id")
            + bytes((EventType(self.event_type),))
            + _rate(self.requested_periodic_rate)
            + _byte(self.event_id, "an event id")
            + _pack_message(self.query_message)
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "UpdateEvent")
        request_id = reader.u8()
        kind = _enum(EventType, reader.u8(), "UpdateEvent event type")
        rate = from_scaled(reader.u16(), 0.0, MAX_EVENT_RATE, 16)
        event_id = reader.u8()
        query = _message(reader, "UpdateEvent")
        reader.end()
        return cls(request_id, kind, rate, event_id, query)


@dataclass(frozen=True, slots=True)
class CancelEvent:
    CODE: ClassVar[int] = MessageCode.CANCEL_EVENT
    request_id: int
    event_id: int

    def to_bytes(self) -> bytes:
        return _byte(self.request_id, "a request id") + _byte(self.event_id, "an event id")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "CancelEvent")
        request_id, event_id = reader.u8(), reader.u8()
        reader.end()
        return cls(request_id, event_id)


@dataclass(frozen=True, slots=True)
class ConfirmEventRequest:
    """Request id u8, event id u8, confirmed periodic rate u16 scaled 0..1092 Hz."""

    CODE: ClassVar[int] = MessageCode.CONFIRM_EVENT_REQUEST
    request_id: int
    event_id: int
    confirmed_periodic_rate: float

    def to_bytes(self) -> bytes:
        return (
            _byte(self.request_id, "a request id")
            + _byte(self.event_id, "an event id")
            + _rate(self.confirmed_periodic_rate)
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ConfirmEventRequest")
        request_id, event_id = reader.u8(), reader.u8()
        rate = from_scaled(reader.u16(), 0.0, MAX_EVENT_RATE, 16)
        reader.end()
        return cls(request_id, event_id, rate)


@dataclass(frozen=True, slots=True)
class RejectEventRequest:
    """Presence vector u8, request id u8, then response code u8 (bit 0) and an error message
    of 80 bytes, NUL-padded (bit 1)."""

    CODE: ClassVar[int] = MessageCode.REJECT_EVENT_REQUEST
    request_id: int
    response_code: EventRejection | None = None
    error_message: str | None = None

    def to_bytes(self) -> bytes:
        presence, body = 0, b""
        if self.response_code is not None:
            presence |= 1
            body += bytes((EventRejection(self.response_code),))
        if self.error_message is not None:
            text = self.error_message.encode()
            if len(text) > 80:
                raise ValueError("an error message is at most 80 bytes")
            presence |= 2
            body += text.ljust(80, b"\0")
        return bytes((presence,)) + _byte(self.request_id, "a request id") + body

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "RejectEventRequest")
        presence = reader.u8()
        if presence >> 2:
            raise JausDecodeError(f"RejectEventRequest: presence vector {presence:#04x}")
        request_id = reader.u8()
        code = (
            _enum(EventRejection, reader.u8(), "RejectEventRequest response code")
            if presence & 1
            else None
        )
        text = reader.take(80).rstrip(b"\0").decode("utf-8", "replace") if presence & 2 else None
        reader.end()
        return cls(request_id, code, text)


@dataclass(frozen=True, slots=True)
class Event:
    """Event id u8, sequence number u8, the report message: count u32 + code and payload."""

    CODE: ClassVar[int] = MessageCode.EVENT
    event_id: int
    sequence_number: int
    report_message: bytes

    def to_bytes(self) -> bytes:
        return (
            _byte(self.event_id, "an event id")
            + _byte(self.sequence_number, "a sequence")
            + _pack_message(self.report_message)
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "Event")
        event_id, sequence = reader.u8(), reader.u8()
        report = _message(reader, "Event")
        reader.end()
        return cls(event_id, sequence, report)


TYPES: tuple[type, ...] = (
    CreateEvent,
    UpdateEvent,
    CancelEvent,
    ConfirmEventRequest,
    RejectEventRequest,
    Event,
)
