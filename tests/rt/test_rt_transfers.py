"""A message sent as several frames (a UPS transfer): the analysis counts every frame."""

from __future__ import annotations

from fractions import Fraction

import pytest

from ups.rt import MessageSpec, analyze

FRAME = Fraction(160 * 2, 1000)  # a worst-case 8-byte 29-bit frame at 500 kbit/s: 0.32 ms


def test_a_transfer_alone_waits_for_its_own_frames() -> None:
    (r,) = analyze([MessageSpec("scan", 8, 100, 100, frames=3)], 500_000)
    # blocked by one frame, then its first two frames, then its last: 4 frames
    assert r.response_time_ms == 4 * FRAME


def test_higher_priority_frames_come_between_a_transfers_frames() -> None:
    hp = MessageSpec("brake", 8, 10, 10)
    scan = MessageSpec("scan", 8, 100, 100, frames=3)
    results = analyze([hp, scan], 500_000)
    assert results[0].response_time_ms == 2 * FRAME  # blocked by one frame of the transfer only
    assert results[1].response_time_ms == 5 * FRAME  # B + 2 own + 1 brake, then its last


def test_a_transfer_interferes_by_all_its_frames() -> None:
    scan = MessageSpec("scan", 8, 100, 100, frames=3)
    low = MessageSpec("low", 8, 100, 100)
    results = analyze([scan, low], 500_000, blocking="lower-priority")
    assert results[1].response_time_ms == 4 * FRAME  # 3 frames of scan, then its own


def test_frames_must_be_positive() -> None:
    with pytest.raises(ValueError, match="frames"):
        MessageSpec("x", 8, 10, 10, frames=0)
