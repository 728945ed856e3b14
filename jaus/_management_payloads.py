"""Payload codecs of the Management service (AS5710A core 1.1 JSIDL: ``CommandClass.xml``,
``QueryClass.xml``, ``InformClass.xml``): shutdown, standby, resume, reset, emergencies, and
the status and timeouts they are queried and reported with. Little-endian; pure functions.
``docs/jaus.md`` ("Payloads") gives the bytes and the sources.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar, Self

from ._codec import Reader
from ._codes import MessageCode
from ._payloads import _byte, _Empty, _enum


class ManagementStatus(IntEnum):
    """Report Status's status."""

    INITIALIZE = 0
    READY = 1
    STANDBY = 2
    SHUTDOWN = 3
    FAILURE = 4
    EMERGENCY = 5


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
)
