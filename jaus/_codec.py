"""What both JAUS framings share: the one error type, JAUS ids, ACK/NAK values, a bounds-checked
reader, and JAUS scaled integers.

Pure functions, no I/O. ``docs/jaus.md`` describes the bytes and cites where each layout comes
from.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum


class JausDecodeError(ValueError):
    """Bytes that are not a well-formed JAUS datagram, message or payload.

    The only exception the decoders raise for bad input, whatever the bytes are.
    """


class AckNak(IntEnum):
    """The 2-bit ACK/NAK field, the same values in AS5669A and in RA 3.3."""

    NONE = 0  #: no acknowledgement wanted
    REQUEST = 1  #: the sender wants an ACK or a NAK
    NAK = 2  #: negative acknowledgement (a response)
    ACK = 3  #: acknowledgement (a response)


RESPONSES = (AckNak.NAK, AckNak.ACK)

BROADCAST_SUBSYSTEM = 0xFFFF  #: subsystem id meaning "every subsystem"
BROADCAST_NODE = 0xFF  #: node id meaning "every node"
BROADCAST_COMPONENT = 0xFF  #: component id meaning "every component"

_ID = struct.Struct("<BBH")  # component, node, subsystem: the u32 of JSIDL's JausID, little-endian


@dataclass(frozen=True, slots=True)
class JausId:
    """A JAUS address: subsystem (u16), node (u8) and component (u8), written
    ``subsystem.node.component``.

    0 is not a valid id part and 0xFF (0xFFFF for the subsystem) means "all", but the codec
    carries every value: routing is the caller's business.
    """

    subsystem: int
    node: int
    component: int

    def __post_init__(self) -> None:
        if not (0 <= self.subsystem <= 0xFFFF and 0 <= self.node <= 0xFF
                and 0 <= self.component <= 0xFF):  # fmt: skip
            raise ValueError(f"JAUS id out of range: {self.subsystem}.{self.node}.{self.component}")

    def __str__(self) -> str:
        return f"{self.subsystem}.{self.node}.{self.component}"

    def to_bytes(self) -> bytes:
        """The 4 bytes on the wire: component, node, subsystem (u16, little-endian)."""
        return _ID.pack(self.component, self.node, self.subsystem)

    @classmethod
    def from_bytes(cls, data: bytes) -> JausId:
        component, node, subsystem = _ID.unpack(data)
        return cls(subsystem, node, component)


class Reader:
    """Reads little-endian fields off ``data``; running short raises :class:`JausDecodeError`."""

    __slots__ = ("_data", "_pos", "_what")

    def __init__(self, data: bytes, what: str, start: int = 0) -> None:
        self._data = data
        self._pos = start
        self._what = what

    @property
    def pos(self) -> int:
        return self._pos

    @property
    def remaining(self) -> int:
        return len(self._data) - self._pos

    def take(self, n: int) -> bytes:
        if n > self.remaining:
            raise JausDecodeError(
                f"{self._what}: {n} more bytes needed at offset {self._pos}, {self.remaining} left"
            )
        chunk = self._data[self._pos : self._pos + n]
        self._pos += n
        return bytes(chunk)

    def u8(self) -> int:
        return self.take(1)[0]

    def u16(self) -> int:
        return int.from_bytes(self.take(2), "little")

    def u32(self) -> int:
        return int.from_bytes(self.take(4), "little")

    def end(self) -> None:
        """Fail unless every byte was read."""
        if self.remaining:
            raise JausDecodeError(f"{self._what}: {self.remaining} unexpected trailing bytes")


def _integer_span(bits: int, signed: bool) -> int:
    if not (2 if signed else 1) <= bits <= 64:
        raise ValueError(f"a JAUS scaled integer has 1-64 bits (2-64 signed), not {bits}")
    return (1 << (bits - 1)) - 1 if signed else (1 << bits) - 1


def _check_range(lower: float, upper: float) -> None:
    if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
        raise ValueError(f"a scaled range needs finite lower < upper, not [{lower}, {upper}]")


def to_scaled(value: float, lower: float, upper: float, bits: int, *, signed: bool = False) -> int:
    """The integer that carries the real ``value`` in a field scaled over [lower, upper].

    Unsigned (JSIDL ``scale_range`` on an unsigned field, as AS6009 uses it)::

        scale = (upper - lower) / (2**bits - 1)      integer = round((value - lower) / scale)

    Signed (``signed=True``; RA 3.3 and JSIDL signed fields)::

        r = 2**(bits - 1) - 1                        integer = round((value - (upper + lower) / 2)
                                                                     * 2 * r / (upper - lower))

    Rounding is half away from zero. A value outside the range by less than half a step is
    clamped; one further out (or NaN) raises ValueError.
    """
    span = _integer_span(bits, signed)
    _check_range(lower, upper)
    if not math.isfinite(value):
        raise ValueError(f"cannot scale {value}")
    if signed:
        steps = (value - (upper + lower) / 2) * 2 * span / (upper - lower)
        low, high = -span, span
    else:
        steps = (value - lower) * span / (upper - lower)
        low, high = 0, span
    if not low - 0.5 <= steps <= high + 0.5:
        raise ValueError(f"{value} is outside the scaled range [{lower}, {upper}]")
    integer = math.floor(steps + 0.5) if steps >= 0 else -math.floor(-steps + 0.5)
    return min(max(integer, low), high)


def from_scaled(
    integer: int, lower: float, upper: float, bits: int, *, signed: bool = False
) -> float:
    """The real value that ``integer`` carries in a field scaled over [lower, upper] (the inverse
    of :func:`to_scaled`): ``integer * scale + lower`` unsigned, ``integer * (upper - lower) /
    (2 r) + (upper + lower) / 2`` signed."""
    span = _integer_span(bits, signed)
    _check_range(lower, upper)
    if signed:
        if not -span <= integer <= span:
            raise ValueError(f"{integer} does not fit a signed {bits}-bit scaled field")
        return integer * (upper - lower) / (2 * span) + (upper + lower) / 2
    if not 0 <= integer <= span:
        raise ValueError(f"{integer} does not fit an unsigned {bits}-bit scaled field")
    return integer * (upper - lower) / span + lower
