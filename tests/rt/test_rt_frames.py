"""Frame lengths: worst-case and no-stuffing bounds, CAN FD, and the exact stuffed length."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ups.rt import frame_bits
from ups.rt._frames import (
    _actual_frame_bits,
    _crc15,
    _stuff_bit_count,
    _stuffable_bits,
    _tindell_frame_bits,
)


@pytest.mark.parametrize(
    ("size", "id_bits", "worst", "none"),
    [
        (8, 11, 135, 111),  # 34 + 64 + 13 + floor(97 / 4)
        (1, 11, 65, 55),
        (0, 11, 55, 47),
        (8, 29, 160, 131),  # 54 + 64 + 13 + floor(117 / 4)
        (1, 29, 90, 75),
        (0, 29, 80, 67),
    ],
)
def test_classic_frame_bits(size: int, id_bits: int, worst: int, none: int) -> None:
    assert frame_bits(size, id_bits) == worst
    assert frame_bits(size, id_bits, "none") == none


def test_defaults_are_29_bit_worst_case() -> None:
    assert frame_bits(8) == 160


def test_paper_000_equation_1_as_its_example_uses_it() -> None:
    """8s + 47 + (34 + 8s) / 5 rounded down: 130 bits for 8 bytes, 63 for 1 (section 4.2)."""
    assert _tindell_frame_bits(8, 11) == 130
    assert _tindell_frame_bits(1, 11) == 63
    assert _tindell_frame_bits(8, 29) == 154


def test_fd_frame_bits() -> None:
    # 11-bit, 8 bytes: 22 + 64 dynamically stuffed (worst floor(85 / 4) = 21), stuff count 4 +
    # CRC-17 with 6 fixed stuff bits, 13 trailing bits.
    assert frame_bits(8, 11, fd=True) == 86 + 21 + 27 + 13
    assert frame_bits(8, 11, "none", fd=True) == 86 + 27 + 13
    # 64 bytes use CRC-21: 4 + 21 + 7 fixed stuff bits.
    assert frame_bits(64, 11, fd=True) == 534 + 133 + 32 + 13
    assert frame_bits(64, 29, fd=True) == 553 + 138 + 32 + 13
    # Sizes between the CAN FD data lengths are padded up.
    assert frame_bits(9, 11, fd=True) == frame_bits(12, 11, fd=True)
    assert frame_bits(13, 11, fd=True) == frame_bits(16, 11, fd=True)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"size_bytes": 9}, "0..8"),
        ({"size_bytes": -1}, "0..8"),
        ({"size_bytes": 65, "fd": True}, "64"),
        ({"size_bytes": 1, "id_bits": 16}, "id_bits"),
        ({"size_bytes": 1, "stuffing": "some"}, "stuffing"),
    ],
)
def test_frame_bits_rejects(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        frame_bits(**kwargs)  # type: ignore[arg-type]


def test_worst_stuffing_pattern_reaches_the_bound() -> None:
    """Five equal bits, then runs of four that join each stuff bit: floor((n - 1) / 4) in n."""
    for n in range(1, 200):
        bits = ([0] * 5 + [1, 1, 1, 1, 0, 0, 0, 0] * 25)[:n]
        assert _stuff_bit_count(bits) == (n - 1) // 4
        assert _stuff_bit_count([0] * n) == n // 5  # a constant run needs fewer


def _stuff(bits: list[int]) -> list[int]:
    """Reference transmitter: insert the complement after five equal bits, stuff bits counted."""
    out: list[int] = []
    for bit in bits:
        out.append(bit)
        if len(out) >= 5 and len(set(out[-5:])) == 1:
            out.append(1 - bit)
    return out


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 1), max_size=150))
def test_stuff_count_matches_reference(bits: list[int]) -> None:
    stuffed = _stuff(bits)
    assert _stuff_bit_count(bits) == len(stuffed) - len(bits)
    runs = "".join(map(str, stuffed))
    assert "000000" not in runs and "111111" not in runs


@settings(max_examples=200, deadline=None)
@given(
    id_bits=st.sampled_from((11, 29)),
    data=st.binary(max_size=8),
    identifier=st.integers(0, (1 << 29) - 1),
)
def test_actual_length_lies_between_the_bounds(id_bits: int, data: bytes, identifier: int) -> None:
    identifier &= (1 << id_bits) - 1
    length = _actual_frame_bits(identifier, data, id_bits)
    assert frame_bits(len(data), id_bits, "none") <= length <= frame_bits(len(data), id_bits)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 1), min_size=1, max_size=120))
def test_crc15_residue_is_zero(bits: list[int]) -> None:
    assert _crc15(bits + _crc15(bits)) == [0] * 15


def test_frame_layout() -> None:
    bits = _stuffable_bits(0x123, b"\xaa", 11)
    assert len(bits) == 34 + 8
    assert bits[:12] == [0, *(int(c) for c in f"{0x123:011b}")]
    assert bits[15:19] == [0, 0, 0, 1]  # DLC = 1
    assert bits[19:27] == [1, 0, 1, 0, 1, 0, 1, 0]
    assert len(_stuffable_bits(0x1ABCDEF, b"", 29)) == 54
    with pytest.raises(ValueError, match="does not fit"):
        _stuffable_bits(1 << 11, b"", 11)
