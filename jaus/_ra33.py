"""The JAUS Reference Architecture 3.3 framing over UDP, as paper 001 (Crouse, *The Joint
Architecture for Unmanned Systems: a subsystem of the Wunderbot 4*) uses it.

A datagram is the 8 ASCII bytes ``JAUS01.0``, the 16-byte RA 3.3 header (every field
little-endian) and the message data: one message per datagram.

Pure functions, no I/O. ``docs/jaus.md`` ("RA 3.3 framing") gives the bytes and the sources.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from ._codec import AckNak, JausDecodeError, Reader

RA33_PREFIX = b"JAUS01.0"
RA33_HEADER_SIZE = 16
RA33_MAX_DATA_SIZE = 4080  #: the largest data of one RA message (data size is 12 bits)
RA33_DEFAULT_PRIORITY = 6
RA33_VERSION = 2  #: the version bits of RA 3.2 and 3.3
RA33_VERSIONS = (0, 1, 2)  #: defined version bits: RA 2.0/2.1, 3.0/3.1, 3.2/3.3


class Ra33DataFlags(IntEnum):
    """The 4 data-flag bits of the data control field: one value at a time."""

    SINGLE = 0
    FIRST = 1
    NORMAL = 2
    RETRANSMITTED = 4
    LAST = 8


_FLAG_VALUES = frozenset(int(flag) for flag in Ra33DataFlags)


@dataclass(frozen=True, slots=True)
class Ra33Address:
    """An RA 3.3 address: subsystem, node, component and instance, one byte each."""

    subsystem: int
    node: int
    component: int
    instance: int = 1

    def __post_init__(self) -> None:
        if not all(0 <= v <= 0xFF for v in (self.subsystem, self.node, self.component,
                                            self.instance)):  # fmt: skip
            raise ValueError(f"RA 3.3 address parts are bytes: {self}")

    def __str__(self) -> str:
        return f"{self.subsystem}.{self.node}.{self.component}.{self.instance}"

    def to_bytes(self) -> bytes:
        """On the wire: instance, component, node, subsystem."""
        return bytes((self.instance, self.component, self.node, self.subsystem))

    @classmethod
    def from_bytes(cls, data: bytes) -> Ra33Address:
        instance, component, node, subsystem = data
        return cls(subsystem, node, component, instance)


@dataclass(frozen=True, slots=True)
class Ra33Header:
    """The 16-byte RA 3.3 header, without its data size (the length of the message's data)."""

    command_code: int
    destination: Ra33Address
    source: Ra33Address
    priority: int = RA33_DEFAULT_PRIORITY
    ack_nak: AckNak = AckNak.NONE
    service_connection: bool = False
    experimental: bool = False
    version: int = RA33_VERSION
    data_flags: Ra33DataFlags = Ra33DataFlags.SINGLE
    sequence: int = 0


@dataclass(frozen=True, slots=True)
class Ra33Message:
    """One RA 3.3 message: its header and its data (the message-specific bytes)."""

    header: Ra33Header
    data: bytes = b""


def encode_ra33(message: Ra33Message) -> bytes:
    """The datagram: ``JAUS01.0``, the 16-byte header, the data. ValueError if a field is out of
    range or the data is longer than 4080 bytes."""
    h = message.header
    if not 0 <= h.priority <= 15:
        raise ValueError(f"RA 3.3 priority is 0-15, not {h.priority}")
    if h.version not in RA33_VERSIONS:
        raise ValueError(f"RA 3.3 version bits {h.version} are not defined")
    if not (0 <= h.command_code <= 0xFFFF and 0 <= h.sequence <= 0xFFFF):
        raise ValueError("command code and sequence number are u16")
    if len(message.data) > RA33_MAX_DATA_SIZE:
        raise ValueError(f"RA 3.3 data is at most {RA33_MAX_DATA_SIZE} bytes")
    properties = (
        h.priority
        | AckNak(h.ack_nak) << 4
        | int(h.service_connection) << 6
        | int(h.experimental) << 7
        | h.version << 8
    )
    control = len(message.data) | Ra33DataFlags(h.data_flags) << 12
    return b"".join((
        RA33_PREFIX,
        properties.to_bytes(2, "little"),
        h.command_code.to_bytes(2, "little"),
        h.destination.to_bytes(),
        h.source.to_bytes(),
        control.to_bytes(2, "little"),
        h.sequence.to_bytes(2, "little"),
        message.data,
    ))  # fmt: skip


def decode_ra33(datagram: bytes) -> Ra33Message:
    """The one message of a ``JAUS01.0`` datagram; :class:`JausDecodeError` for anything else
    (a short datagram, another prefix, undefined version or flag bits, a data size above 4080,
    more or fewer data bytes than the header declares)."""
    if datagram[: len(RA33_PREFIX)] != RA33_PREFIX:
        raise JausDecodeError("not a JAUS01.0 datagram")
    reader = Reader(datagram, "RA 3.3", start=len(RA33_PREFIX))
    if reader.remaining < RA33_HEADER_SIZE:
        raise JausDecodeError(f"RA 3.3 header of {reader.remaining} bytes, not 16")
    properties = reader.u16()
    version = (properties >> 8) & 0x3F
    if version not in RA33_VERSIONS:
        raise JausDecodeError(f"RA 3.3 version bits {version} are not defined")
    if properties >> 14:
        raise JausDecodeError("RA 3.3 reserved property bits are set")
    command_code = reader.u16()
    destination = Ra33Address.from_bytes(reader.take(4))
    source = Ra33Address.from_bytes(reader.take(4))
    control = reader.u16()
    flag_bits = control >> 12
    if flag_bits not in _FLAG_VALUES:
        raise JausDecodeError(f"RA 3.3 data flags {flag_bits:#06b} (one flag at a time)")
    size = control & 0x0FFF
    if size > RA33_MAX_DATA_SIZE:
        raise JausDecodeError(f"RA 3.3 data size {size} exceeds {RA33_MAX_DATA_SIZE}")
    sequence = reader.u16()
    if size != reader.remaining:
        raise JausDecodeError(f"RA 3.3 data size {size}, but {reader.remaining} bytes follow")
    header = Ra33Header(
        command_code=command_code,
        destination=destination,
        source=source,
        priority=properties & 0x0F,
        ack_nak=AckNak((properties >> 4) & 3),
        service_connection=bool(properties & 0x40),
        experimental=bool(properties & 0x80),
        version=version,
        data_flags=Ra33DataFlags(flag_bits),
        sequence=sequence,
    )
    return Ra33Message(header, reader.take(size))
