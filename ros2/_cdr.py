"""CDR as ROS 2 puts it on the wire, compiled once per message type.

A serialized message is a 4-byte encapsulation header, ``00 01 00 00`` (plain CDR,
little-endian), then the message's values in order, each aligned to its own size counted from
the end of the header (8-byte values to 8), strings as a uint32 length (with the terminating
NUL), the bytes and the NUL, sequences as a uint32 count and their elements. A message of
fixed size (no string, no sequence) is padded with zeros to a multiple of 4 bytes, as rclpy's
``serialize_message`` makes it (rmw_zenoh's own publishers leave that padding out; every CDR
reader ignores it). Padding is zeros here; rclpy leaves whatever its buffer held.

``Codec(items)`` turns a message's flattened items (``_types``) into a program: runs of
primitives become one ``struct.Struct`` for each of the 8 alignments a run can start at, so
that encoding and decoding a message is a few ``pack``/``unpack_from`` calls and never looks
at the definition again. A message of primitives only is one ``pack``.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence as Seq
from typing import Any

from ups import DecodeError

from ._types import PRIMITIVES, STRING, Item, Sequence, Value

HEADER = b"\x00\x01\x00\x00"  #: CDR_LE, no options
_U32 = struct.Struct("<I")


class CdrError(DecodeError):
    """A payload that is not CDR of the expected message."""


def _pad(pos: int, size: int) -> int:
    return -pos % size


class _Run:
    """Consecutive primitives: a struct per starting position modulo 8."""

    __slots__ = ("slots", "structs")

    def __init__(self, slots: list[int], codes: list[str]) -> None:
        self.slots = slots
        self.structs = []
        for start in range(8):
            fmt, pos = "<", start
            for code in codes:
                size = struct.calcsize(code)
                pad = _pad(pos, size)
                fmt += "x" * pad + code
                pos += pad + size
            self.structs.append(struct.Struct(fmt))

    def encode(self, out: bytearray, pos: int, values: Seq[Any]) -> int:
        s = self.structs[pos & 7]
        out += s.pack(*[values[i] for i in self.slots])
        return pos + s.size

    def decode(self, data: bytes, pos: int, values: list[Any] | None) -> int:
        s = self.structs[pos & 7]
        got = s.unpack_from(data, 4 + pos)
        if values is not None:
            for slot, value in zip(self.slots, got, strict=True):
                values[slot] = value
        return pos + s.size


class _String:
    __slots__ = ("bound", "slot")

    def __init__(self, slot: int, bound: int) -> None:
        self.slot, self.bound = slot, bound

    def encode(self, out: bytearray, pos: int, values: Seq[Any]) -> int:
        text = str(values[self.slot]).encode("utf-8")
        pad = _pad(pos, 4)
        out += b"\x00" * pad + _U32.pack(len(text) + 1) + text + b"\x00"
        return pos + pad + 4 + len(text) + 1

    def decode(self, data: bytes, pos: int, values: list[Any] | None) -> int:
        pos += _pad(pos, 4)
        size: int = _U32.unpack_from(data, 4 + pos)[0]
        start, end = 4 + pos + 4, 4 + pos + 4 + size
        if size == 0 or end > len(data) or data[end - 1] != 0:
            raise CdrError("a string without its terminating NUL")
        if values is not None:
            try:
                values[self.slot] = data[start : end - 1].decode("utf-8")
            except UnicodeDecodeError:
                raise CdrError("a string that is not UTF-8") from None
        return pos + 4 + size


class _Sequence:
    """Sent empty; skipped when received."""

    __slots__ = ("element", "size")

    def __init__(self, element: str | tuple[Item, ...]) -> None:
        self.element: Codec | str = element if isinstance(element, str) else Codec(element)
        self.size = struct.calcsize(PRIMITIVES[element]) if element in PRIMITIVES else 0

    def encode(self, out: bytearray, pos: int, values: Seq[Any]) -> int:
        pad = _pad(pos, 4)
        out += b"\x00" * pad + _U32.pack(0)
        return pos + pad + 4

    def decode(self, data: bytes, pos: int, values: list[Any] | None) -> int:
        pos += _pad(pos, 4)
        count: int = _U32.unpack_from(data, 4 + pos)[0]
        pos += 4
        if count > len(data):  # every element takes a byte at least
            raise CdrError(f"a sequence of {count} elements in {len(data)} bytes")
        if self.size:
            pos += _pad(pos, self.size) if count else 0
            return pos + count * self.size
        for _ in range(count):
            if isinstance(self.element, Codec):
                pos = self.element.skip(data, pos)
            else:
                pos = _String(0, 0).decode(data, pos, None)
        return pos


class Codec:
    """Encode and decode one message type, given its flattened items. Values are a list with
    one entry per ``Value`` item (``self.values``), in order."""

    def __init__(self, items: tuple[Item, ...]) -> None:
        self.values: tuple[Value, ...] = tuple(i for i in items if isinstance(i, Value))
        self._ops: list[_Run | _String | _Sequence] = []
        run_slots: list[int] = []
        run_codes: list[str] = []
        slot = 0
        for item in items:
            if isinstance(item, Value) and item.type != STRING:
                run_slots.append(slot)
                run_codes.append(PRIMITIVES[item.type])
                slot += 1
                continue
            if run_slots:
                self._ops.append(_Run(run_slots, run_codes))
                run_slots, run_codes = [], []
            if isinstance(item, Value):
                self._ops.append(_String(slot, item.bound))
                slot += 1
            else:
                assert isinstance(item, Sequence)
                self._ops.append(_Sequence(item.element))
        if run_slots:
            self._ops.append(_Run(run_slots, run_codes))
        only = self._ops[0] if len(self._ops) == 1 else None
        self._fixed = only.structs[0] if isinstance(only, _Run) else None
        self._fixed_pad = b"\x00" * (-self._fixed.size % 4) if self._fixed is not None else b""

    def zeros(self) -> list[Any]:
        """A message whose every value is zero (strings empty)."""
        return ["" if v.type == STRING else False if v.type == "bool" else 0 for v in self.values]

    def encode(self, values: Seq[Any]) -> bytes:
        """The serialized message; ``struct.error`` (or ``OverflowError``) for a value its
        type cannot hold."""
        if self._fixed is not None:
            return HEADER + self._fixed.pack(*values) + self._fixed_pad
        out = bytearray(HEADER)
        pos = 0
        for op in self._ops:
            pos = op.encode(out, pos, values)
        return bytes(out)

    def decode(self, data: bytes) -> list[Any]:
        """The message's values; ``CdrError`` when ``data`` is not this message in CDR."""
        if data[:2] != HEADER[:2]:
            raise CdrError(f"not little-endian plain CDR (header {data[:4].hex() or '-'})")
        values: list[Any] = [None] * len(self.values)
        try:
            pos = 0
            for op in self._ops:
                pos = op.decode(data, pos, values)
        except struct.error:
            raise CdrError(f"{len(data)} bytes are too few for the message") from None
        if 4 + pos > len(data):
            raise CdrError(f"{len(data)} bytes are too few for the message")
        return values

    def skip(self, data: bytes, pos: int) -> int:
        """The position after one such message at ``pos`` (inside a sequence)."""
        for op in self._ops:
            pos = op.decode(data, pos, None)
        return pos
