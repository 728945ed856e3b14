"""CAN frame lengths in bits: worst-case and no-stuffing bounds, and the exact stuffed length.

Classic CAN (Davis et al. 2007): a data frame with ``s`` data bytes has ``g + 8s`` bits
subject to bit stuffing (SOF to the end of the CRC; ``g`` is 34 with 11-bit and 54 with 29-bit
identifiers) and 13 more that are not (CRC delimiter, ACK slot and delimiter, 7 bits end of frame
and the 3-bit interframe space). At most ``floor((g + 8s - 1) / 4)`` stuff bits are inserted, so
the worst case is ``g + 8s + 13 + floor((g + 8s - 1) / 4)`` bits: 135 for 8 bytes with an 11-bit
identifier, 160 with a 29-bit one. All lengths here include the interframe space, so a frame's
time on the bus is its length times the bit time and the next arbitration starts right after.

CAN FD (ISO 11898-1:2015), counted at one bit rate (no bit-rate switch): ``22`` (11-bit) or
``41`` (29-bit) header bits plus the data are dynamically stuffed, then the 4-bit stuff count and
a 17-bit (up to 16 data bytes) or 21-bit CRC carry a fixed stuff bit before the stuff count and
after every fourth bit, then the same 13 trailing bits.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

Stuffing = Literal["worst", "none"]

_STUFFED_HEADER = {11: 34, 29: 54}
"""Bits subject to stuffing apart from the data (``g``), classic frames."""
_TRAILER = 13
"""CRC delimiter, ACK slot, ACK delimiter, 7 EOF bits, 3 interframe bits."""
_FD_HEADER = {11: 22, 29: 41}
_FD_SIZES = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def _check_id_bits(id_bits: int) -> None:
    if id_bits not in _STUFFED_HEADER:
        raise ValueError(f"id_bits must be 11 or 29, not {id_bits}")


def _fd_payload_size(size_bytes: int) -> int:
    """Return the CAN FD data field length that carries ``size_bytes`` (padded up to a DLC size)."""
    for size in _FD_SIZES:
        if size >= size_bytes:
            return size
    raise ValueError(f"a CAN FD frame carries at most 64 data bytes, not {size_bytes}")


def frame_bits(
    size_bytes: int,
    id_bits: int = 29,
    stuffing: Stuffing = "worst",
    fd: bool = False,
) -> int:
    """Return the length in bits of a CAN data frame, interframe space included.

    ``stuffing="worst"`` gives the worst case over all identifiers and payloads,
    ``stuffing="none"`` the length without any dynamic stuff bits (CAN FD's fixed stuff bits are
    always counted). Classic frames carry 0..8 bytes; with ``fd=True`` up to 64, rounded up to the
    next CAN FD data length, all bits counted at the arbitration bit rate.
    """
    _check_id_bits(id_bits)
    if stuffing not in ("worst", "none"):
        raise ValueError(f"stuffing must be 'worst' or 'none', not {stuffing!r}")
    if fd:
        size = _fd_payload_size(size_bytes)
        dynamic = _FD_HEADER[id_bits] + 8 * size
        crc = 17 if size <= 16 else 21
        fixed = 4 + crc + (4 + crc + 3) // 4
        stuff = (dynamic - 1) // 4 if stuffing == "worst" else 0
        return dynamic + stuff + fixed + _TRAILER
    if not 0 <= size_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {size_bytes}")
    stuffed = _STUFFED_HEADER[id_bits] + 8 * size_bytes
    stuff = (stuffed - 1) // 4 if stuffing == "worst" else 0
    return stuffed + _TRAILER + stuff


def _tindell_frame_bits(size_bytes: int, id_bits: int) -> int:
    """Frame length as in Tindell & Burns (1994): ``8s + g + 13 + floor((g + 8s) / 5)``.

    For 11-bit identifiers this is the ``8s + 47 + (34 + 8s) / 5`` of paper 000's equation (1)
    with the quotient rounded down, which is what its worked example uses (130 bits for 8 bytes,
    63 for 1). It under-counts the worst case, which needs ``floor((g + 8s - 1) / 4)`` stuff bits.
    """
    _check_id_bits(id_bits)
    if not 0 <= size_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {size_bytes}")
    stuffed = _STUFFED_HEADER[id_bits] + 8 * size_bytes
    return stuffed + _TRAILER + stuffed // 5


def _crc15(bits: Sequence[int]) -> list[int]:
    """CAN's CRC-15 (polynomial 0x4599) of a bit sequence, most significant bit first."""
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= 0x4599
    return [(crc >> shift) & 1 for shift in range(14, -1, -1)]


def _bits(value: int, width: int) -> list[int]:
    return [(value >> shift) & 1 for shift in range(width - 1, -1, -1)]


def _stuffable_bits(identifier: int, data: bytes, id_bits: int) -> list[int]:
    """The bits of a classic data frame from SOF to the end of the CRC, before stuffing."""
    _check_id_bits(id_bits)
    if not 0 <= identifier < (1 << id_bits):
        raise ValueError(f"identifier {identifier:#x} does not fit in {id_bits} bits")
    if len(data) > 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {len(data)}")
    if id_bits == 11:
        # SOF, identifier, RTR, IDE, r0
        head = [0, *_bits(identifier, 11), 0, 0, 0]
    else:
        # SOF, base identifier, SRR, IDE, identifier extension, RTR, r1, r0
        head = [0, *_bits(identifier >> 18, 11), 1, 1, *_bits(identifier, 18), 0, 0, 0]
    body = [*head, *_bits(len(data), 4)]
    for byte in data:
        body.extend(_bits(byte, 8))
    return body + _crc15(body)


def _stuff_bit_count(bits: Sequence[int]) -> int:
    """Stuff bits a transmitter inserts: one of opposite value after five equal bits in a row.

    Inserted bits count towards the next run, as on the bus.
    """
    count = 0
    previous = -1
    run = 0
    for bit in bits:
        if bit == previous:
            run += 1
        else:
            previous = bit
            run = 1
        if run == 5:
            count += 1
            previous = 1 - bit
            run = 1
    return count


def _actual_frame_bits(identifier: int, data: bytes, id_bits: int) -> int:
    """The exact length in bits of one classic data frame on the bus, interframe space included."""
    bits = _stuffable_bits(identifier, data, id_bits)
    return len(bits) + _stuff_bit_count(bits) + _TRAILER
