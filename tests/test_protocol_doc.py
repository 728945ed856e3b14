"""docs/protocol.md must stay true: every example frame in it is checked against the codec."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from ups import _canproto as p
from ups import name_to_uid

DOC = (Path(__file__).resolve().parent.parent / "docs" / "protocol.md").read_text()
ROW = re.compile(r"^\| `([0-9A-F]{8})` \| (?:`([0-9a-f ]+)`|-) \| (.+?) \|$", re.M)
EVENT = re.compile(r"event: priority (0x[0-9A-F]+), TxNode (\d+), etag (0x[0-9A-F]+)")
EXAMPLES = ROW.findall(DOC.split("### Worked example", 1)[1])


def test_the_example_table_is_found() -> None:
    assert len(EXAMPLES) >= 15


@pytest.mark.parametrize(("ident", "data", "frame"), EXAMPLES)
def test_example_frame(ident: str, data: str, frame: str) -> None:
    can_id, payload = int(ident, 16), bytes.fromhex(data)
    event = EVENT.fullmatch(frame)
    if event:
        priority, txnode, etag = (int(x, 0) for x in event.groups())
        assert not p.is_management(can_id)
        assert can_id == p.make_id(priority, txnode, etag)
        return
    expected = eval(frame.strip("`"), {"__builtins__": {}}, vars(p))  # our own doc, our names
    assert p.encode(expected) == (can_id, payload)
    assert p.decode(can_id, payload) == expected


def test_documented_uids() -> None:
    for name, uid in re.findall(r"`([a-z/]+)` →\s+`(0x[0-9a-f]{16})`", DOC):
        assert name_to_uid(name) == int(uid, 16)


def test_documented_constants() -> None:
    assert "0x00\u20130x7E (127 nodes)" in DOC and p.TXNODE_COUNT == 127 and p.MGMT_TXNODE == 0x7F
    assert "0x0010\u20130x3FFF" in DOC and (p.FIRST_ETAG, p.LAST_ETAG) == (0x10, 0x3FFF)
    assert "0x80 by default" in DOC and p.DEFAULT_PRIORITY == 0x80


TCP_ROW = re.compile(r"^\| `([0-9a-f ]+)` \| `([^`]+)`", re.M)
TCP_EXAMPLES = TCP_ROW.findall(DOC.split("## TCP/IP framing", 1)[1].split("## UPS on Zenoh")[0])


@pytest.mark.parametrize(("raw", "frame"), TCP_EXAMPLES)
def test_tcp_example_frame(raw: str, frame: str) -> None:
    from ups import _tcpwire as w

    expected = eval(frame, {"__builtins__": {}}, vars(w))  # our own doc, our names
    assert w.encode(expected) == bytes.fromhex(raw)
    assert w.Decoder().feed(bytes.fromhex(raw)) == [expected]


def test_tcp_examples_are_found() -> None:
    assert len(TCP_EXAMPLES) == 11


TRANSFER_ROW = re.compile(r"^\| `([0-9a-f ]+)` \| (\d+) \| ((?:`[0-9a-f ]+`(?:, )?)+) \|$", re.M)
TRANSFERS = TRANSFER_ROW.findall(DOC.split("### Events larger than one frame", 1)[1])


def test_the_transfer_examples_are_found() -> None:
    assert len(TRANSFERS) == 2


@pytest.mark.parametrize(("event", "tid", "frames"), TRANSFERS)
def test_transfer_example(event: str, tid: str, frames: str) -> None:
    from ups import _cantransfer as t

    expected = [bytes.fromhex(f) for f in re.findall(r"`([0-9a-f ]+)`", frames)]
    assert t.segment(bytes.fromhex(event), int(tid), 8) == expected
    r = t.Reassembler()
    got = [r.feed((0, 0x3000), f, False, 64, 0.0) for f in expected]
    assert got[-1] == bytes.fromhex(event)


ZENOH = DOC.split("## UPS on Zenoh", 1)[1]
ZENOH_ROW = re.compile(
    r"^\| channel `([^`]+)`, priority (0x[0-9A-F]+), node (0x[0-9A-F]+), number (\d+) "
    r"\| `(ups/[^`]+)` \| `([0-9a-f ]+)` \|$",
    re.M,
)
ZENOH_EXAMPLES = ZENOH_ROW.findall(ZENOH)


def test_zenoh_examples_are_found() -> None:
    assert len(ZENOH_EXAMPLES) == 3


@pytest.mark.parametrize(("channel", "priority", "node", "seq", "key", "raw"), ZENOH_EXAMPLES)
def test_zenoh_example(
    channel: str, priority: str, node: str, seq: str, key: str, raw: str
) -> None:
    from ups import _zenohface as z
    from ups._channel import parse_channel

    chan = parse_channel(channel)
    assert z.channel_key(chan.uid, chan.name) == key
    assert z.ATTACHMENT.pack(
        z.VERSION, int(priority, 16), int(node, 16), int(seq)
    ) == bytes.fromhex(raw)


def test_zenoh_priority_table() -> None:
    from ups import _zenohface as z

    rows = re.findall(r"^\| 0x([0-9A-F]{2})\u20130x([0-9A-F]{2}) \| (\d) ", ZENOH, re.M)
    assert len(rows) == 7
    for low, high, band in rows:
        assert {z.to_zenoh_priority(p) for p in range(int(low, 16), int(high, 16) + 1)} == {
            int(band)
        }
        assert z.from_zenoh_priority(int(band)) == int(low, 16)
