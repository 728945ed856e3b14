"""JUDP: the SAE JAUS UDP transport of AS5669A (transport version 2).

A datagram is one version byte (2) followed by one or more messages. Each message is the
12-byte general transport header (14 with the header-compression fields), the transported data
(for a whole message: the 2-byte message code, little-endian, then the payload) and a 2-byte
sequence number. Large messages travel as several such messages, marked by the data flags.

Pure functions, no I/O. ``docs/jaus.md`` ("JUDP") gives the bytes and the sources.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from enum import IntEnum

from ._codec import RESPONSES, AckNak, JausDecodeError, JausId, Reader

JUDP_PORT = 3794  #: the UDP port IANA assigned to JAUS
JUDP_VERSION = 2  #: the first byte of every AS5669A datagram
HEADER_SIZE = 12  #: general transport header without the header-compression fields
HC_FIELDS_SIZE = 2  #: HC number and HC length, present when the HC flags are not 0
SEQUENCE_SIZE = 2
MIN_DATA_SIZE = HEADER_SIZE + SEQUENCE_SIZE  #: 14: a bare header (an ACK/NAK response)
MAX_DATA_SIZE = 0xFFFF  #: the data size field is a u16
DEFAULT_PART_SIZE = 4079  #: largest transported data per message when splitting (Junior's cap)
CODE_SIZE = 2


class Priority(IntEnum):
    LOW = 0
    STANDARD = 1
    HIGH = 2
    SAFETY_CRITICAL = 3


class Broadcast(IntEnum):
    NONE = 0
    LOCAL = 1
    GLOBAL = 2  # 3 is undefined: a decode error


class DataFlags(IntEnum):
    """Where this message stands in a large message split over several."""

    SINGLE = 0
    FIRST = 1
    NORMAL = 2
    LAST = 3


class HcFlags(IntEnum):
    NONE = 0  #: no header compression (no HC number and HC length bytes)
    REQUEST = 1  #: the sender asks to engage header compression
    RESPONSE = 2  #: the answer; its meaning depends on the HC length
    COMPRESSED = 3  #: the data is compressed: this codec cannot read it (a decode error)


@dataclass(frozen=True, slots=True)
class JudpHeader:
    """The general transport header of one message, and the sequence number that trails it."""

    destination: JausId
    source: JausId
    priority: Priority = Priority.STANDARD
    broadcast: Broadcast = Broadcast.NONE
    ack_nak: AckNak = AckNak.NONE
    data_flags: DataFlags = DataFlags.SINGLE
    sequence: int = 0
    hc_flags: HcFlags = HcFlags.NONE
    hc_number: int = 0
    hc_length: int = 0


@dataclass(frozen=True, slots=True)
class JudpMessage:
    """One message of a JUDP datagram.

    ``code`` is the message code (None in an ACK/NAK response, which carries no data, and in the
    NORMAL and LAST parts of a large message, whose data continues the FIRST part's). ``payload``
    is the rest of the transported data. Unknown codes are carried as they are.
    """

    header: JudpHeader
    code: int | None
    payload: bytes = b""


def rules_error(header: JudpHeader, code: int | None, payload_len: int) -> str | None:
    """What is wrong with this combination of header flags and data, or None."""
    if header.ack_nak in RESPONSES:
        if code is not None or payload_len:
            return "an ACK/NAK response carries no data"
    elif header.data_flags in (DataFlags.SINGLE, DataFlags.FIRST):
        if code is None:
            return "a single or first message starts with a message code"
    elif code is not None:
        return "a NORMAL or LAST part carries no message code of its own"
    return None


def _encode_one(message: JudpMessage, out: bytearray) -> None:
    h = message.header
    problem = rules_error(h, message.code, len(message.payload))
    if problem:
        raise ValueError(problem)
    if h.hc_flags == HcFlags.COMPRESSED:
        raise ValueError("header-compressed data is not supported")
    if not 0 <= h.sequence <= 0xFFFF:
        raise ValueError(f"sequence number out of range: {h.sequence}")
    hc = h.hc_flags != HcFlags.NONE
    if not hc and (h.hc_number or h.hc_length):
        raise ValueError("HC number and HC length need HC flags")
    if not (0 <= h.hc_number <= 0xFF and 0 <= h.hc_length <= 0xFF):
        raise ValueError("HC number and HC length are bytes")
    data = b""
    if message.code is not None:
        if not 0 <= message.code <= 0xFFFF:
            raise ValueError(f"message code out of range: {message.code:#x}")
        data = message.code.to_bytes(2, "little")
    data += message.payload
    size = MIN_DATA_SIZE + (HC_FIELDS_SIZE if hc else 0) + len(data)
    if size > MAX_DATA_SIZE:
        raise ValueError(f"message of {size} bytes: JUDP carries at most {MAX_DATA_SIZE}")
    out.append(HcFlags(h.hc_flags) << 6)  # message type 0 in bits 0-5, HC flags in 6-7
    out += size.to_bytes(2, "little")
    if hc:
        out += bytes((h.hc_number, h.hc_length))
    out.append(
        Priority(h.priority)
        | Broadcast(h.broadcast) << 2
        | AckNak(h.ack_nak) << 4
        | DataFlags(h.data_flags) << 6
    )
    out += h.destination.to_bytes() + h.source.to_bytes() + data
    out += h.sequence.to_bytes(2, "little")


def encode_judp(messages: Iterable[JudpMessage]) -> bytes:
    """One datagram carrying ``messages`` (at least one) behind the version byte.

    Raises ValueError for a message that cannot be sent as given (see :class:`JudpMessage`).
    """
    out = bytearray((JUDP_VERSION,))
    for message in messages:
        _encode_one(message, out)
    if len(out) == 1:
        raise ValueError("a JUDP datagram carries at least one message")
    return bytes(out)


def _decode_one(reader: Reader, datagram: bytes) -> JudpMessage:
    start = reader.pos
    type_hc = reader.u8()
    if type_hc & 0x3F:
        raise JausDecodeError(f"JUDP message type {type_hc & 0x3F} (only 0 is defined)")
    hc_flags = HcFlags(type_hc >> 6)
    if hc_flags == HcFlags.COMPRESSED:
        raise JausDecodeError("header-compressed JUDP message (not supported)")
    size = reader.u16()
    hc_number = hc_length = 0
    if hc_flags != HcFlags.NONE:
        hc_number, hc_length = reader.u8(), reader.u8()
    least = MIN_DATA_SIZE + (HC_FIELDS_SIZE if hc_flags else 0)
    if size < least:
        raise JausDecodeError(f"JUDP data size {size} is smaller than its header ({least})")
    if size > len(datagram) - start:
        raise JausDecodeError(
            f"JUDP data size {size}, but only {len(datagram) - start} bytes arrived"
        )
    flags = reader.u8()
    if (flags >> 2) & 3 == 3:
        raise JausDecodeError("JUDP broadcast flags 3 (undefined)")
    destination = JausId.from_bytes(reader.take(4))
    source = JausId.from_bytes(reader.take(4))
    data = reader.take(start + size - SEQUENCE_SIZE - reader.pos)
    header = JudpHeader(
        destination=destination,
        source=source,
        priority=Priority(flags & 3),
        broadcast=Broadcast((flags >> 2) & 3),
        ack_nak=AckNak((flags >> 4) & 3),
        data_flags=DataFlags(flags >> 6),
        sequence=reader.u16(),
        hc_flags=hc_flags,
        hc_number=hc_number,
        hc_length=hc_length,
    )
    code: int | None = None
    payload = data
    carries_code = header.ack_nak not in RESPONSES and header.data_flags in (
        DataFlags.SINGLE,
        DataFlags.FIRST,
    )
    if carries_code and len(data) >= CODE_SIZE:
        code, payload = int.from_bytes(data[:2], "little"), data[2:]
    problem = rules_error(header, code, len(payload))
    if problem:
        raise JausDecodeError(f"JUDP: {problem}")
    return JudpMessage(header, code, payload)


def decode_judp(datagram: bytes) -> list[JudpMessage]:
    """Every message of one JUDP datagram, in order.

    Raises :class:`JausDecodeError` (and nothing else) when any part of the datagram is not
    well formed: the whole datagram is then to be dropped.
    """
    if not datagram:
        raise JausDecodeError("empty datagram")
    if datagram[0] != JUDP_VERSION:
        raise JausDecodeError(
            f"JUDP transport version {datagram[0]} (this codec reads {JUDP_VERSION}, AS5669A)"
        )
    reader = Reader(datagram, "JUDP", start=1)
    if not reader.remaining:
        raise JausDecodeError("JUDP datagram without a message")
    messages = []
    while reader.remaining:
        messages.append(_decode_one(reader, datagram))
    return messages


def split_message(
    header: JudpHeader,
    code: int,
    payload: bytes,
    *,
    max_part: int = DEFAULT_PART_SIZE,
    code_in_every_part: bool = False,
) -> list[JudpMessage]:
    """The JUDP messages that carry message ``code`` with ``payload`` from ``header``'s source.

    One SINGLE message when the code and payload fit ``max_part`` bytes, else a FIRST, NORMAL
    ... and LAST part of at most ``max_part`` transported bytes each, numbered from
    ``header.sequence`` up (mod 65536): the sender's next sequence number is then
    ``header.sequence + len(result)``. By default the message code travels once, at the start
    of the FIRST part (as JTS's Junior does); ``code_in_every_part`` repeats it at the start of
    every part (as JAUS++ does).
    """
    if header.data_flags != DataFlags.SINGLE or header.ack_nak in RESPONSES:
        raise ValueError("split a message given by a SINGLE, non-response header")
    if not 0 <= code <= 0xFFFF:
        raise ValueError(f"message code out of range: {code:#x}")
    if max_part < CODE_SIZE + 1:
        raise ValueError(f"max_part must leave room for data after the code, not {max_part}")
    if CODE_SIZE + len(payload) <= max_part:
        return [JudpMessage(header, code, payload)]
    code_bytes = code.to_bytes(2, "little")
    if code_in_every_part:
        step = max_part - CODE_SIZE
        chunks = [code_bytes + payload[i : i + step] for i in range(0, len(payload), step)]
    else:
        data = code_bytes + payload
        chunks = [data[i : i + max_part] for i in range(0, len(data), max_part)]
    parts = []
    for i, chunk in enumerate(chunks):
        flags = DataFlags.FIRST if i == 0 else DataFlags.NORMAL
        if i == len(chunks) - 1:
            flags = DataFlags.LAST
        part_header = replace(header, data_flags=flags, sequence=(header.sequence + i) & 0xFFFF)
        if i == 0:
            parts.append(JudpMessage(part_header, code, chunk[CODE_SIZE:]))
        else:
            parts.append(JudpMessage(part_header, None, chunk))
    return parts
