"""Payload codecs of the List Manager service (AS5710A core, ``ListManager.xml``) and what the
Local Waypoint List Driver (AS6009 mobility) adds to it: Execute List and the active element.
Little-endian; pure functions. ``docs/jaus.md`` gives the bytes.

A list element is a record: its UID (1..65534), the UIDs of the elements before and after it
(0: none), and its data -- a format byte (0: a JAUS message, its code and payload) and a u16
count of bytes. A Local Waypoint List Driver's elements are Set Local Waypoint messages.

None of these can be mapped onto a channel (``MAPPABLE``): the list is the component's own
state, and each waypoint reaches the robot as its Set Local Waypoint mapping says.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar, Self

from ._codec import JausDecodeError, Reader, from_scaled, to_scaled
from ._codes import MessageCode
from ._payloads import _byte, _Empty

ALL_ELEMENTS = 0xFFFF  #: Delete Element's UID for "every element"
NO_ELEMENT = 0  #: a previous or next UID for "none": the head's previous, the tail's next
JAUS_MESSAGE = 0  #: an element's data format: a JAUS message (code u16 LE, then its payload)


class ElementRejection(IntEnum):
    """Reject Element Request's response codes."""

    INVALID_ELEMENT_ID = 1
    INVALID_PREVIOUS_ELEMENT = 2
    INVALID_NEXT_ELEMENT = 3
    UNSUPPORTED_ELEMENT_TYPE = 4
    ELEMENT_NOT_FOUND = 5
    OUT_OF_MEMORY = 6
    UNSPECIFIED_ERROR = 7


def _u16(value: int, what: str) -> bytes:
    if not 0 <= value <= 0xFFFF:
        raise ValueError(f"{what} is 0-65535, not {value}")
    return value.to_bytes(2, "little")


@dataclass(frozen=True, slots=True)
class Element:
    """UID u16, previous UID u16, next UID u16, data format u8, data count u16, data."""

    uid: int
    previous: int
    next: int
    data: bytes
    format: int = JAUS_MESSAGE

    def to_bytes(self) -> bytes:
        if len(self.data) > 0xFFFF:
            raise ValueError(f"an element's data is at most 65535 bytes, not {len(self.data)}")
        return (
            _u16(self.uid, "an element UID")
            + _u16(self.previous, "a previous UID")
            + _u16(self.next, "a next UID")
            + _byte(self.format, "an element data format")
            + len(self.data).to_bytes(2, "little")
            + self.data
        )

    @classmethod
    def read(cls, reader: Reader) -> Self:
        uid, previous, following = reader.u16(), reader.u16(), reader.u16()
        kind = reader.u8()
        return cls(uid, previous, following, reader.take(reader.u16()), kind)


@dataclass(frozen=True, slots=True)
class _ListMessage:
    CODE: ClassVar[int]
    MAPPABLE: ClassVar[bool] = False


@dataclass(frozen=True, slots=True)
class SetElement(_ListMessage):
    """Request id u8, element count u8, the elements."""

    CODE: ClassVar[int] = MessageCode.SET_ELEMENT
    request_id: int
    elements: tuple[Element, ...]

    def to_bytes(self) -> bytes:
        if len(self.elements) > 0xFF:
            raise ValueError(f"Set Element carries at most 255 elements, not {len(self.elements)}")
        body = b"".join(e.to_bytes() for e in self.elements)
        return _byte(self.request_id, "a request id") + bytes([len(self.elements)]) + body

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        request_id, count = reader.u8(), reader.u8()
        elements = tuple(Element.read(reader) for _ in range(count))
        reader.end()
        return cls(request_id, elements)


@dataclass(frozen=True, slots=True)
class DeleteElement(_ListMessage):
    """Request id u8, UID count u8, the UIDs (u16; 65535: every element)."""

    CODE: ClassVar[int] = MessageCode.DELETE_ELEMENT
    request_id: int
    uids: tuple[int, ...]

    def to_bytes(self) -> bytes:
        if len(self.uids) > 0xFF:
            raise ValueError(f"Delete Element names at most 255 UIDs, not {len(self.uids)}")
        body = b"".join(_u16(uid, "an element UID") for uid in self.uids)
        return _byte(self.request_id, "a request id") + bytes([len(self.uids)]) + body

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        request_id, count = reader.u8(), reader.u8()
        uids = tuple(reader.u16() for _ in range(count))
        reader.end()
        return cls(request_id, uids)


@dataclass(frozen=True, slots=True)
class _Uid(_ListMessage):
    """One element UID, u16."""

    uid: int

    def to_bytes(self) -> bytes:
        return _u16(self.uid, "an element UID")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        uid = reader.u16()
        reader.end()
        return cls(uid)


@dataclass(frozen=True, slots=True)
class QueryElement(_Uid):
    CODE: ClassVar[int] = MessageCode.QUERY_ELEMENT


@dataclass(frozen=True, slots=True)
class ReportActiveElement(_Uid):
    """The UID of the element being executed (0: none)."""

    CODE: ClassVar[int] = MessageCode.REPORT_ACTIVE_ELEMENT


@dataclass(frozen=True, slots=True)
class ReportElementCount(_ListMessage):
    """Element count u16."""

    CODE: ClassVar[int] = MessageCode.REPORT_ELEMENT_COUNT
    count: int

    def to_bytes(self) -> bytes:
        return _u16(self.count, "an element count")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        count = reader.u16()
        reader.end()
        return cls(count)


@dataclass(frozen=True, slots=True)
class ReportElement(_ListMessage):
    """One element record, as in Set Element."""

    CODE: ClassVar[int] = MessageCode.REPORT_ELEMENT
    element: Element

    def to_bytes(self) -> bytes:
        return self.element.to_bytes()

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        element = Element.read(reader)
        reader.end()
        return cls(element)


@dataclass(frozen=True, slots=True)
class ReportElementList(_ListMessage):
    """UID count u16, the UIDs (u16) from head to tail."""

    CODE: ClassVar[int] = MessageCode.REPORT_ELEMENT_LIST
    uids: tuple[int, ...]

    def to_bytes(self) -> bytes:
        body = b"".join(_u16(uid, "an element UID") for uid in self.uids)
        return _u16(len(self.uids), "an element count") + body

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        count = reader.u16()
        uids = tuple(reader.u16() for _ in range(count))
        reader.end()
        return cls(uids)


@dataclass(frozen=True, slots=True)
class ConfirmElementRequest(_ListMessage):
    """Request id u8."""

    CODE: ClassVar[int] = MessageCode.CONFIRM_ELEMENT_REQUEST
    request_id: int

    def to_bytes(self) -> bytes:
        return _byte(self.request_id, "a request id")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        request_id = reader.u8()
        reader.end()
        return cls(request_id)


@dataclass(frozen=True, slots=True)
class RejectElementRequest(_ListMessage):
    """Request id u8, response code u8 (:class:`ElementRejection`)."""

    CODE: ClassVar[int] = MessageCode.REJECT_ELEMENT_REQUEST
    request_id: int
    response: ElementRejection

    def to_bytes(self) -> bytes:
        return _byte(self.request_id, "a request id") + bytes([int(self.response)])

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        request_id, code = reader.u8(), reader.u8()
        reader.end()
        try:
            return cls(request_id, ElementRejection(code))
        except ValueError:
            raise JausDecodeError(f"{cls.__name__}: response code {code} is not 1-7") from None


@dataclass(frozen=True, slots=True)
class ExecuteList(_ListMessage):
    """Presence vector u8; speed u16 scaled 0..327.67 m/s; bit 0: the UID to start at (u16;
    absent: the head)."""

    CODE: ClassVar[int] = MessageCode.EXECUTE_LIST
    speed: float
    start: int | None = None

    def to_bytes(self) -> bytes:
        presence = 0 if self.start is None else 1
        body = bytes([presence]) + to_scaled(self.speed, 0.0, 327.67, 16).to_bytes(2, "little")
        return body if self.start is None else body + _u16(self.start, "an element UID")

    @classmethod
    def from_bytes(cls, data: bytes) -> Self:
        reader = Reader(data, cls.__name__)
        presence = reader.u8()
        if presence & ~1:
            raise JausDecodeError(
                f"{cls.__name__}: presence vector {presence:#04x} has bits above 0"
            )
        speed = from_scaled(reader.u16(), 0.0, 327.67, 16)
        start = reader.u16() if presence & 1 else None
        reader.end()
        return cls(speed, start)


@dataclass(frozen=True, slots=True)
class QueryElementList(_ListMessage, _Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_ELEMENT_LIST


@dataclass(frozen=True, slots=True)
class QueryElementCount(_ListMessage, _Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_ELEMENT_COUNT


@dataclass(frozen=True, slots=True)
class QueryActiveElement(_ListMessage, _Empty):
    CODE: ClassVar[int] = MessageCode.QUERY_ACTIVE_ELEMENT


TYPES: tuple[type, ...] = (
    SetElement,
    DeleteElement,
    QueryElement,
    QueryElementList,
    QueryElementCount,
    ReportElement,
    ReportElementList,
    ReportElementCount,
    ConfirmElementRequest,
    RejectElementRequest,
    ExecuteList,
    QueryActiveElement,
    ReportActiveElement,
)
