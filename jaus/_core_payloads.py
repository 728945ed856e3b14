"""Payload codecs of the core services the component host serves beyond control: Management,
Events and Discovery's configuration and services (AS5710A core 1.1 JSIDL: ``CommandClass.xml``,
``QueryClass.xml``, ``InformClass.xml``, ``BasicTypes.xml``). Little-endian; pure functions.
``docs/jaus.md`` ("Payloads") gives the bytes and the sources.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar, Self

from ._codec import JausDecodeError, Reader, from_scaled, to_scaled
from ._codes import MessageCode
from ._payloads import _byte, _Empty, _enum

MAX_EVENT_RATE = 1092.0  #: Hz: the upper end of Create Event's scaled periodic rate


class ManagementStatus(IntEnum):
    """Report Status's status."""

    INITIALIZE = 0
    READY = 1
    STANDBY = 2
    SHUTDOWN = 3
    FAILURE = 4
    EMERGENCY = 5


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


# --- Management -------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Shutdown(_Empty):
    CODE: ClassVar[int] = MessageCode.SHUTDOWN


@dataclass(frozen=True, slots=True)
class Standby(_Empty):
    CODE: ClassVar[int] = MessageCode.STANDBY


@dataclass(frozen=True, slots=True)
class Resume(_Empty):
    CODE: ClassVar[int] = MessageCode.RESUME


@dataclass(frozen=True, slots=True)
class Reset(_Empty):
    CODE: ClassVar[int] = MessageCode.RESET


@dataclass(frozen=True, slots=True)
class QueryStatus(_Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_STATUS


@dataclass(frozen=True, slots=True)
class QueryTimeout(_Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_TIMEOUT


@dataclass(frozen=True, slots=True)
class QueryEventTimeout(_Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_EVENT_TIMEOUT


@dataclass(frozen=True, slots=True)
class _Emergency:
    """Emergency code: u16, 1 STOP (other values carried)."""

    CODE: ClassVar[int]
    emergency_code: int = 1

    def to_bytes(self) -> bytes:
        if not 0 <= self.emergency_code <= 0xFFFF:
            raise ValueError("an emergency code is a u16")
        return self.emergency_code.to_bytes(2, "little")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        code = reader.u16()
        reader.end()
        return cls(code)


@dataclass(frozen=True, slots=True)
class SetEmergency(_Emergency):
    CODE: ClassVar[int] = MessageCode.SET_EMERGENCY


@dataclass(frozen=True, slots=True)
class ClearEmergency(_Emergency):
    CODE: ClassVar[int] = MessageCode.CLEAR_EMERGENCY


@dataclass(frozen=True, slots=True)
class ReportStatus:
    """Status u8, then a reserved u32 (sent as 0, carried)."""

    CODE: ClassVar[int] = MessageCode.REPORT_STATUS
    status: ManagementStatus
    reserved: int = 0

    def to_bytes(self) -> bytes:
        return bytes((ManagementStatus(self.status),)) + self.reserved.to_bytes(4, "little")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportStatus")
        status = _enum(ManagementStatus, reader.u8(), "ReportStatus status")
        reserved = reader.u32()
        reader.end()
        return cls(status, reserved)


@dataclass(frozen=True, slots=True)
class _Timeout:
    """One u8: seconds (Report Timeout) or minutes (Report Event Timeout); 0: no timeout."""

    CODE: ClassVar[int]
    timeout: int

    def to_bytes(self) -> bytes:
        return _byte(self.timeout, "a timeout")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        value = reader.u8()
        reader.end()
        return cls(value)


@dataclass(frozen=True, slots=True)
class ReportTimeout(_Timeout):
    CODE: ClassVar[int] = MessageCode.REPORT_TIMEOUT


@dataclass(frozen=True, slots=True)
class ReportEventTimeout(_Timeout):
    CODE: ClassVar[int] = MessageCode.REPORT_EVENT_TIMEOUT


# --- Events -----------------------------------------------------------------------------------


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


# --- Discovery: configuration and services ----------------------------------------------------


@dataclass(frozen=True, slots=True)
class QueryConfiguration:
    CODE: ClassVar[int] = MessageCode.QUERY_CONFIGURATION
    query_type: int = 2  # subsystem

    def to_bytes(self) -> bytes:
        return _byte(self.query_type, "a query type")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "QueryConfiguration")
        value = reader.u8()
        reader.end()
        return cls(value)


@dataclass(frozen=True, slots=True)
class Service:
    uri: str
    major: int
    minor: int


@dataclass(frozen=True, slots=True)
class ComponentEntry:
    component: int
    instance: int = 1
    services: tuple[Service, ...] = ()


@dataclass(frozen=True, slots=True)
class NodeEntry:
    node: int
    components: tuple[ComponentEntry, ...]


def _count(items: tuple[object, ...], what: str) -> bytes:
    if len(items) > 0xFF:
        raise ValueError(f"at most 255 {what}")
    return bytes((len(items),))


@dataclass(frozen=True, slots=True)
class ReportConfiguration:
    """Node list (count u8; node id u8, component list (count u8; component id u8, instance
    id u8))."""

    CODE: ClassVar[int] = MessageCode.REPORT_CONFIGURATION
    nodes: tuple[NodeEntry, ...]

    def to_bytes(self) -> bytes:
        out = bytearray(_count(self.nodes, "nodes"))
        for node in self.nodes:
            out += _byte(node.node, "a node id") + _count(node.components, "components")
            for c in node.components:
                out += _byte(c.component, "a component id") + _byte(c.instance, "an instance")
        return bytes(out)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportConfiguration")
        nodes = []
        for _ in range(reader.u8()):
            node = reader.u8()
            comps = tuple(ComponentEntry(reader.u8(), reader.u8()) for _ in range(reader.u8()))
            nodes.append(NodeEntry(node, comps))
        reader.end()
        return cls(tuple(nodes))


@dataclass(frozen=True, slots=True)
class QueryServices:
    """Node list (count u8, at least 1; node id u8, component list (count u8, at least 1;
    component id u8)); 255 stands for every node or component."""

    CODE: ClassVar[int] = MessageCode.QUERY_SERVICES
    nodes: tuple[tuple[int, tuple[int, ...]], ...] = ((0xFF, (0xFF,)),)

    def to_bytes(self) -> bytes:
        out = bytearray(_count(self.nodes, "nodes"))
        for node, comps in self.nodes:
            out += _byte(node, "a node id") + _count(comps, "components")
            out += b"".join(_byte(c, "a component id") for c in comps)
        return bytes(out)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "QueryServices")
        nodes = []
        for _ in range(reader.u8()):
            node = reader.u8()
            nodes.append((node, tuple(reader.u8() for _ in range(reader.u8()))))
        reader.end()
        return cls(tuple(nodes))


@dataclass(frozen=True, slots=True)
class ReportServices:
    """Node list (count u8; node id u8, component list (count u8; component id u8, instance id
    u8, service list (count u8; URI: count u8 + bytes, major u8, minor u8)))."""

    CODE: ClassVar[int] = MessageCode.REPORT_SERVICES
    nodes: tuple[NodeEntry, ...]

    def to_bytes(self) -> bytes:
        out = bytearray(_count(self.nodes, "nodes"))
        for node in self.nodes:
            out += _byte(node.node, "a node id") + _count(node.components, "components")
            for c in node.components:
                out += _byte(c.component, "a component id") + _byte(c.instance, "an instance")
                out += _count(c.services, "services")
                for s in c.services:
                    uri = s.uri.encode()
                    if len(uri) > 0xFF:
                        raise ValueError("a service URI is at most 255 bytes")
                    out += bytes((len(uri),)) + uri
                    out += _byte(s.major, "a version") + _byte(s.minor, "a version")
        return bytes(out)

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, "ReportServices")
        nodes = []
        for _ in range(reader.u8()):
            node, comps = reader.u8(), []
            for _ in range(reader.u8()):
                component, instance = reader.u8(), reader.u8()
                services = []
                for _ in range(reader.u8()):
                    uri = reader.take(reader.u8()).decode("utf-8", "replace")
                    services.append(Service(uri, reader.u8(), reader.u8()))
                comps.append(ComponentEntry(component, instance, tuple(services)))
            nodes.append(NodeEntry(node, tuple(comps)))
        reader.end()
        return cls(tuple(nodes))


TYPES: tuple[type, ...] = (
    Shutdown,
    Standby,
    Resume,
    Reset,
    QueryStatus,
    QueryTimeout,
    QueryEventTimeout,
    SetEmergency,
    ClearEmergency,
    ReportStatus,
    ReportTimeout,
    ReportEventTimeout,
    CreateEvent,
    UpdateEvent,
    CancelEvent,
    ConfirmEventRequest,
    RejectEventRequest,
    Event,
    QueryConfiguration,
    ReportConfiguration,
    QueryServices,
    ReportServices,
)
