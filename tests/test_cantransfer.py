"""The transfer codec: round trips, and what the reassembler makes of damaged frame sequences.

The invariant: the reassembler returns only events that were sent, each whole; every transfer
it does not return is counted in ``lost``.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ups import _canproto as p
from ups import _cantransfer as t

events = st.binary(max_size=3000)
mtus = st.sampled_from([8, 64])


def test_crc_check_value() -> None:
    assert t.crc16(b"123456789") == 0x29B1


def test_size_classes_cover_the_etags() -> None:
    assert t.class_etags(0) == range(p.FIRST_ETAG, 0x3000)
    assert [t.class_etags(c).start for c in range(1, 5)] == [0x3000, 0x3400, 0x3800, 0x3C00]
    assert t.class_etags(4).stop == p.LAST_ETAG + 1
    for cls in range(5):
        assert {t.size_class(e) for e in t.class_etags(cls)} == {cls}
    assert [t.class_for(n) for n in (0, 8, 9, 64, 65, 1024, 1025, 4096, 4097, 65535)] == [
        0, 0, 1, 1, 2, 2, 3, 3, 4, 4,
    ]  # fmt: skip
    with pytest.raises(ValueError, match="at most 65535"):
        t.class_for(65536)


def test_frame_layout_by_hand() -> None:
    # 9 bytes, classic: stream = 00 09 | 9 bytes | crc (2) = 13 bytes -> 7 + 6
    event = bytes(range(1, 10))
    crc = t.crc16(event).to_bytes(2, "big")
    first, last = t.segment(event, 5, 8)
    assert first == bytes([0x80 | 0x20 | 5, 0x00, 0x09]) + event[:5]
    assert last == bytes([0x40 | 5]) + event[5:] + crc
    # 5 bytes fit one frame: no CRC
    assert t.segment(b"hello", 31, 8) == [bytes([0xC0 | 0x20 | 31, 0, 5]) + b"hello"]
    # FD: the last frame is padded with zeros to a CAN FD length
    (only,) = t.segment(bytes(10), 0, 64)
    assert len(only) == 16 and only[:3] == bytes([0xE0, 0, 10])


@given(event=events, tid=st.integers(0, 31), mtu=mtus)
def test_round_trip(event: bytes, tid: int, mtu: int) -> None:
    frames = t.segment(event, tid, mtu)
    assert len(frames) == t.frames_for(len(event), mtu)
    assert all(len(f) == mtu for f in frames[:-1])
    r = t.Reassembler()
    results = [r.feed((1, 0x3C00), f, mtu == 64, t.MAX_EVENT, 0.0) for f in frames]
    assert results[:-1] == [None] * (len(frames) - 1)
    assert results[-1] == event
    assert (r.lost, r.frames_dropped, r.pending) == (0, 0, 0)


@st.composite
def damaged(draw: st.DrawFn) -> tuple[list[bytes], list[tuple[int, bytes]], bool]:
    """Several events' frames, each tagged with its event, then some lost, repeated, swapped,
    or with a payload bit flipped in a transfer of several frames (a single frame is guarded
    by the CAN frame's own CRC)."""
    mtu = draw(mtus)
    sent = draw(st.lists(st.binary(max_size=400), min_size=1, max_size=6, unique=True))
    frames = [(i, f) for i, e in enumerate(sent) for f in t.segment(e, i, mtu)]
    for _ in range(draw(st.integers(0, 4))):
        i = draw(st.integers(0, len(frames) - 1))
        what = draw(st.sampled_from(["lose", "repeat", "swap", "flip"]))
        event = frames[i][0]
        if what == "lose" and len(frames) > 1:
            del frames[i]
        elif what == "repeat":
            frames.insert(i, frames[i])
        elif what == "swap" and i + 1 < len(frames):
            frames[i], frames[i + 1] = frames[i + 1], frames[i]
        elif what == "flip" and t.frames_for(len(sent[event]), mtu) > 1 and len(frames[i][1]) > 3:
            f = bytearray(frames[i][1])
            bit = draw(st.integers(8 * 3, 8 * len(f) - 1))  # past the header and length
            f[bit // 8] ^= 1 << (bit % 8)
            frames[i] = (event, bytes(f))
    return sent, frames, mtu == 64


@settings(max_examples=500)
@given(case=damaged())
def test_damage_never_makes_a_wrong_event_and_every_loss_is_counted(
    case: tuple[list[bytes], list[tuple[int, bytes]], bool],
) -> None:
    sent, frames, fd = case
    r = t.Reassembler()
    got = [e for _, f in frames if (e := r.feed((1, 0x3C00), f, fd, t.MAX_EVENT, 0.0)) is not None]
    r.expire(10.0)
    assert set(got) <= set(sent)  # a repeated one-frame event may come twice; never a wrong one
    touched = {event for event, _ in frames}  # a frame of it reached the receiver
    assert len(set(got)) + r.lost >= len(touched)
    assert r.pending == 0


def test_a_length_beyond_the_class_is_refused() -> None:
    r = t.Reassembler()
    frames = t.segment(bytes(100), 0, 8)
    assert [r.feed((1, 0x3000), f, False, 64, 0.0) for f in frames] == [None] * len(frames)
    assert r.lost >= 1


def test_bounded_reassembly_gives_up_the_oldest() -> None:
    r = t.Reassembler(max_transfers=2)
    for sender in range(3):
        r.feed((sender, 0x3400), t.segment(bytes(100), 0, 8)[0], False, 1024, 0.0)
    assert (r.pending, r.evicted, r.lost) == (2, 1, 1)
    assert r.expire(5.0) == 2
    assert r.lost == 3


@pytest.mark.parametrize("missing", [1, 2, 5])
def test_one_broken_transfer_is_one_loss(missing: int) -> None:
    frames = t.segment(bytes(range(100)), 4, 8)
    r = t.Reassembler()
    for f in frames[:missing] + frames[missing + 1 :]:
        assert r.feed((1, 0x3400), f, False, 1024, 0.0) is None
    assert (r.lost, r.pending) == (1, 0)
    assert r.feed((1, 0x3400), t.segment(b"next", 5, 8)[0], False, 1024, 0.0) == b"next"
    assert r.lost == 1
