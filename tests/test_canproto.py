"""The CAN identifier layout and every management frame, against docs/protocol.md."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ups import DecodeError
from ups import _canproto as p

u64 = st.integers(0, (1 << 64) - 1)
nibble = st.integers(0, 15)


def test_identifier_layout_is_priority_txnode_etag() -> None:
    assert p.make_id(0xAB, 0x55, 0x1234) == (0xAB << 21) | (0x55 << 14) | 0x1234
    assert p.make_id(0xFF, 0x7F, 0x3FFF) == (1 << 29) - 1
    assert p.split_id(0x1FFFFFFF) == (0xFF, 0x7F, 0x3FFF)


@given(st.integers(0, 255), st.integers(0, 127), st.integers(0, 0x3FFF))
def test_identifier_round_trip(priority: int, txnode: int, etag: int) -> None:
    assert p.split_id(p.make_id(priority, txnode, etag)) == (priority, txnode, etag)


@given(st.integers(0, 255), st.integers(0, 255), st.integers(0, 126), st.integers(0, 126))
def test_priority_decides_arbitration(a: int, b: int, node_a: int, node_b: int) -> None:
    """A lower priority value wins arbitration (lower identifier) whatever the TxNodes."""
    if a < b:
        assert p.make_id(a, node_a, 0x3FFF) < p.make_id(b, node_b, p.FIRST_ETAG)


def test_management_space() -> None:
    assert p.is_management(p.make_id(0x80, p.MGMT_TXNODE, 0x100))
    assert p.is_management(p.make_id(0x00, 5, 0x0002))
    assert p.is_management(p.make_id(0x00, 5, p.FIRST_ETAG))  # SUB_AT
    assert p.is_management(p.make_id(0x01, 5, p.FIRST_ETAG))  # PUB_AT
    assert not p.is_management(p.make_id(p.FIRST_EVENT_PRIORITY, 5, p.FIRST_ETAG))


management = st.one_of(
    st.builds(p.Stage, st.integers(0, 15), st.integers(0, 15), nibble),
    st.builds(p.Query, st.integers(0, 15), st.lists(nibble, min_size=1, max_size=15).map(tuple)),
    st.builds(p.Assign, st.integers(0, 126), u64),
    st.builds(p.Offer, st.integers(0, 126), u64),
    st.builds(p.Census, st.integers(0, 15)),
    st.builds(p.Knock),
    st.builds(p.Hello, u64),
    st.builds(p.Serving, u64),
    st.builds(p.Probe, u64),
    st.builds(p.TxNodesFull, u64),
    st.builds(p.EtagsFull, u64),
    st.builds(p.Failed, u64),
    st.builds(p.Limit, st.integers(0, 126), u64),
    st.builds(
        p.Holds, st.booleans(), st.integers(0, 126), st.integers(p.FIRST_ETAG, p.LAST_ETAG), u64
    ),
    st.builds(p.Bind, st.integers(p.FIRST_ETAG, p.LAST_ETAG), u64),
    st.builds(
        p.Grant, st.integers(p.FIRST_ETAG, p.LAST_ETAG), st.integers(0, 126), st.integers(0, 255)
    ),
    st.builds(
        p.Refuse,
        st.integers(p.FIRST_ETAG, p.LAST_ETAG),
        st.integers(0, 126),
        st.integers(p.FIRST_ETAG, p.LAST_ETAG),
        st.integers(0, 126),
        st.integers(0, 0xFFFF),
    ),
    st.builds(  # a one-frame etag: the event's size, 0..8 bytes
        p.Declare,
        st.integers(0, 126),
        st.integers(p.FIRST_ETAG, p.LARGE_FIRST_ETAG - 1),
        st.integers(0, 8),
        st.integers(1, 0xFFFF),
        st.integers(1, 0xFFFF),
        st.integers(0, 255),
    ),
    st.builds(  # a larger size class's etag: the event's frames, 1..255
        p.Declare,
        st.integers(0, 126),
        st.integers(p.LARGE_FIRST_ETAG, p.LAST_ETAG),
        st.integers(1, 255),
        st.integers(1, 0xFFFF),
        st.integers(1, 0xFFFF),
        st.integers(0, 255),
    ),
    st.builds(
        p.Request,
        st.sampled_from([p.PUB_BIND, p.SUB_BIND, p.UNSUB, p.CLAIM]),
        st.integers(0, 126),
        u64,
    ),
)


@given(management)
def test_management_round_trip(msg: p.Management) -> None:
    can_id, data = p.encode(msg)
    assert can_id < 1 << 29 and len(data) <= 8
    assert p.is_management(can_id)
    assert p.decode(can_id, data) == msg


@given(st.integers(0, (1 << 29) - 1), st.binary(max_size=8))
def test_decode_never_fails_other_than_decode_error(can_id: int, data: bytes) -> None:
    if not p.is_management(can_id):
        return
    try:
        msg = p.decode(can_id, data)
    except DecodeError:
        return
    assert p.encode(msg) == (can_id, data)  # whatever decodes, encodes back to the same bytes


@pytest.mark.parametrize(
    ("can_id", "data", "why"),
    [
        (p.make_id(0, 0x7F, 0x0123), b"\x00", "stage carries no data"),
        (p.make_id(0, 0x7F, 0x1100), b"\x10" + bytes(7), "query prefix does not match its nibble"),
        (p.make_id(0, 0x7F, 0x1100), b"\x01" + bytes(7), "query has nibbles past its length"),
        (p.make_id(0, 0x7F, 0x1FF0), bytes(8), "query of a whole id (16 nibbles)"),
        (p.make_id(0, 0x7F, 0x3F00), b"\x00", "knock carries no data"),
        (p.make_id(0, 0x7F, 0x3010), b"", "census epoch out of range"),
        (p.make_id(0, 0x7F, 0x387F), bytes(8), "limit names the reserved TxNode"),
        (p.make_id(1, 3, 0x0100), bytes(7), "PUB_AT without a full UID"),
        (p.make_id(0, 0x7F, 0x207F), bytes(8), "assignment of the reserved TxNode"),
        (p.make_id(0, 0x7F, 0x20FF), bytes(8), "offer of the reserved TxNode"),
        (p.make_id(0, 0x7F, 0x2100), bytes(8), "assignment argument out of range"),
        (p.make_id(0, 0x7F, 0x3E00), b"", "unknown status"),
        (p.make_id(1, 0x7F, 0x0005), bytes(8), "binding of a reserved etag"),
        (p.make_id(1, 0x7F, 0x0100), bytes(7), "binding without a full UID"),
        (p.make_id(2, 0x7F, 0x0100), bytes(8), "unknown management priority"),
        (p.make_id(0, 3, 0x000F), bytes(8), "unknown node request"),
        (p.make_id(5, 3, 0x0001), bytes(8), "node request at the wrong priority"),
    ],
)
def test_malformed_management_is_a_decode_error(can_id: int, data: bytes, why: str) -> None:
    with pytest.raises(DecodeError):
        p.decode(can_id, data)


def test_nibbles_most_significant_first() -> None:
    assert p.nibbles_of(0x0123456789ABCDEF) == tuple(range(16))
