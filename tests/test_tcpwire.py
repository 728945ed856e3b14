"""The TCP framing: round trips, streams cut anywhere, and bad bytes as one clear error."""

from __future__ import annotations

import msgpack
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ups import DecodeError
from ups import _tcpwire as w

u64 = st.integers(0, (1 << 64) - 1)
port = st.integers(0, 0xFFFF)
peer = st.builds(w.Peer, u64, st.text(max_size=40), port)
frames = st.one_of(
    st.builds(w.Hello, u64, st.text(max_size=40), st.text(max_size=40), port),
    st.builds(w.Event, u64, st.binary(max_size=300), st.integers(0, 255), u64),
    st.builds(w.Start, u64, u64),
    st.builds(w.Subscribe, u64),
    st.builds(w.Unsubscribe, u64),
    st.builds(w.Advertise, u64),
    st.builds(w.Unadvertise, u64),
    st.builds(w.Subscribers, u64, st.lists(peer, max_size=5).map(tuple)),
    st.just(w.Ping()),
    st.just(w.Pong()),
)


@given(st.lists(frames, max_size=8), st.data())
def test_stream_round_trip_cut_anywhere(sent: list[w.Frame], data: st.DataObject) -> None:
    stream = b"".join(w.encode(f) for f in sent)
    assert _fed_in_pieces(stream, data, max_cuts=6) == sent


def _fed_in_pieces(stream: bytes, data: st.DataObject, max_cuts: int) -> list[w.Frame]:
    """What one Decoder makes of ``stream`` fed in pieces cut where Hypothesis draws."""
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=max_cuts)))
    decoder = w.Decoder()
    got: list[w.Frame] = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        got += decoder.feed(stream[a:b])
    return got


def test_event_fast_path_is_the_same_bytes() -> None:
    assert w.encode_event(7, b"\x01\x02", 0x20, 3) == w.encode(w.Event(7, b"\x01\x02", 0x20, 3))
    head = w.event_header(7, 2, 0x20, 3)
    assert len(head) == w.EVENT_HEADER and head + b"\x01\x02" == w.encode_event(
        7, b"\x01\x02", 0x20, 3
    )


def test_header_layout() -> None:
    frame = w.encode(w.Ping())
    assert frame == bytes([2, 0, 0, 2]) + msgpack.packb([7])  # version 2, body of 2 bytes
    event = w.encode(w.Event(0x0102030405060708, b"xy", 0x80, 9))
    assert event == bytes([2, 0, 0, 20, 1, 0x80, 1, 2, 3, 4, 5, 6, 7, 8]) + bytes(7) + b"\x09xy"


@given(u64, st.binary(max_size=300), st.integers(0, 255), u64, st.integers(0, 40))
def test_events_among_short_control_frames(
    uid: int, data: bytes, priority: int, seq: int, pings: int
) -> None:
    """A short control frame at the end of a read is not mistaken for an event, nor the other
    way round, whatever the mix."""
    sent = [w.Ping()] * pings + [w.Event(uid, data, priority, seq), w.Pong()]
    stream = b"".join(w.encode(f) for f in sent)
    decoder = w.Decoder()
    got = [f for i in range(len(stream)) for f in decoder.feed(stream[i : i + 1])]
    assert got == sent


# sizes around the last one decoded with a single struct call (256), and equal to a Start's
sized_events = st.builds(
    w.Event,
    u64,
    st.sampled_from([0, 1, 8, 17, 255, 256, 257, 300]).map(bytes),
    st.integers(0, 255),
    u64,
)


@given(
    st.lists(st.one_of(sized_events, st.builds(w.Start, u64, u64), st.just(w.Ping())), max_size=40),
    st.data(),
)
def test_runs_of_events_of_changing_sizes(sent: list[w.Frame], data: st.DataObject) -> None:
    """The decoder reads an event with the layout of the previous one's size: a run of equal
    sizes, a size that changes, or a control frame in between, each comes out as it went in."""
    stream = b"".join(w.encode(f) for f in sent)
    assert w.Decoder().feed(stream) == sent
    assert _fed_in_pieces(stream, data, max_cuts=4) == sent


@given(st.binary(max_size=64))
def test_arbitrary_bytes_decode_or_raise_decode_error(junk: bytes) -> None:
    try:
        for frame in w.Decoder().feed(junk):
            assert isinstance(frame, w.Frame)
    except DecodeError:
        pass


def _raw(body: bytes, version: int = 2) -> bytes:
    return bytes([version]) + len(body).to_bytes(3, "big") + body


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        (_raw(b"\x90", version=1), "unsupported UPS/TCP version 1"),
        (bytes([2, 0x10, 0, 0]), "exceeds the limit"),
        (_raw(b"\xc1"), "not msgpack"),
        (_raw(b"\x07"), "array starting with its kind"),
        (_raw(msgpack.packb([99])), "unknown frame kind 99"),
        (_raw(msgpack.packb([1, 1, b"", 0, 1])), "unknown frame kind 1"),  # events are binary
        (_raw(b"\x01" + bytes(16)), "event frame of 17 bytes"),
        (_raw(b"\x01"), "event frame of 1 bytes"),
        (_raw(msgpack.packb([11, 1])), "bad frame"),
        (_raw(b"\x91" * 5000 + b"\x01"), "not msgpack|nested|bad frame|kind"),
        (_raw(msgpack.packb([2, 1, 2])), "bad frame"),
        (_raw(msgpack.packb([6, 1, [[1, "h"]]])), "bad frame"),
    ],
)
def test_bad_frames_are_decode_errors(raw: bytes, why: str) -> None:
    with pytest.raises(DecodeError, match=why):
        w.Decoder(max_frame=1 << 16).feed(raw)


def test_oversized_event_is_refused_before_its_body_arrives() -> None:
    decoder = w.Decoder(max_frame=100)
    big = w.encode(w.Event(1, bytes(200), 0, 1))
    with pytest.raises(DecodeError, match="exceeds the limit of 100"):
        decoder.feed(big[:4])
