"""The document's worked examples, decoded and encoded by ``_frames`` (built from the tables
alone): the tables and the examples of docs/protocol.md agree with each other."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from ups import name_to_uid

from ._frames import (
    CLAIM,
    PUB_BIND,
    SUB_BIND,
    UNSUB,
    Assign,
    Bind,
    Census,
    Declare,
    EtagsFull,
    Event,
    Failed,
    Frame,
    Grant,
    Hello,
    Knock,
    Limit,
    Offer,
    Probe,
    PubAt,
    Query,
    Refuse,
    Request,
    Serving,
    Stage,
    SubAt,
    TxNodesFull,
    decode_id,
    encode,
)

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
SPEED = 0xBBCCB9C002D5ED59

#: every example row of the CAN section: identifier, data (hex, or "-"), the frame it names
EXAMPLES: list[tuple[str, str, Frame]] = [
    ("001FF300", "01 23 45 67 89 ab cd ef", Hello(0x0123456789ABCDEF)),
    ("001FFF00", "-", Knock()),
    ("001FF000", "-", Census(0)),
    ("001FC000", "-", Stage(0, 0, 0)),
    ("001FC010", "-", Stage(0, 1, 0)),
    ("001FC0E5", "-", Stage(0, 14, 5)),
    ("001FC0FB", "-", Stage(0, 15, 11)),
    ("001FE080", "00 00 00 00 00 00 00 5b", Offer(0, 0x5B)),
    ("00000004", "00 00 00 00 00 00 00 5b", Request(CLAIM, 0, 0x5B)),
    ("001FE000", "00 00 00 00 00 00 00 5b", Assign(0, 0x5B)),
    ("00000002", "bb cc b9 c0 02 d5 ed 59", Request(SUB_BIND, 0, SPEED)),
    ("003FC010", "bb cc b9 c0 02 d5 ed 59", Bind(0x10, SPEED)),
    ("00004001", "bb cc b9 c0 02 d5 ed 59", Request(PUB_BIND, 1, SPEED)),
    ("04004010", "01 02", Event(0x20, 1, 0x10, b"\x01\x02")),
    ("00000003", "bb cc b9 c0 02 d5 ed 59", Request(UNSUB, 0, SPEED)),
    ("001FF001", "-", Census(1)),
    ("001FC100", "-", Stage(1, 0, 0)),
    ("001FC1E2", "-", Stage(1, 14, 2)),
    ("001FC1E3", "-", Stage(1, 14, 3)),
    ("001FC1F5", "-", Stage(1, 15, 5)),
    ("001FC1FA", "-", Stage(1, 15, 10)),
    ("001FD2E2", "00 00 00 00 00 00 00 20", Query(2, (0,) * 14 + (2,))),
    ("001FD3E3", "00 00 00 00 00 00 00 30", Query(3, (0,) * 14 + (3,))),
    ("001FC2F5", "-", Stage(2, 15, 5)),
    ("001FC3FA", "-", Stage(3, 15, 10)),
    ("001FE082", "00 00 00 00 00 00 00 25", Offer(2, 0x25)),
    ("001FE083", "00 00 00 00 00 00 00 3a", Offer(3, 0x3A)),
    ("00008004", "00 00 00 00 00 00 00 25", Request(CLAIM, 2, 0x25)),
    ("0000C004", "00 00 00 00 00 00 00 3a", Request(CLAIM, 3, 0x3A)),
    ("001FE002", "00 00 00 00 00 00 00 25", Assign(2, 0x25)),
    ("001FE003", "00 00 00 00 00 00 00 3a", Assign(3, 0x3A)),
    ("001FF300", "0f ed cb a9 87 65 43 21", Hello(0x0FEDCBA987654321)),
    ("00000004", "00 00 00 00 00 00 00 5b", Request(CLAIM, 0, 0x5B)),
    ("00000010", "bb cc b9 c0 02 d5 ed 59", SubAt(0, 0x10, SPEED)),
    ("00004004", "00 00 00 00 00 00 00 9b", Request(CLAIM, 1, 0x9B)),
    ("00204010", "bb cc b9 c0 02 d5 ed 59", PubAt(1, 0x10, SPEED)),
    ("001FF600", "01 23 45 67 89 ab cd ef", Serving(0x0123456789ABCDEF)),
    ("001FF900", "01 23 45 67 89 ab cd ef", Probe(0x0123456789ABCDEF)),
    ("001FF100", "00 00 00 00 00 00 be ef", TxNodesFull(0xBEEF)),
    ("001FF200", "00 00 00 00 00 00 12 34", EtagsFull(0x1234)),
    ("001FF700", "00 00 00 00 00 00 12 34", Failed(0x1234)),
    ("001FF804", "00 00 00 00 00 00 12 34", Limit(4, 0x1234)),
    ("00004005", "00 11 01 00 64 00 32 00", Declare(1, 0x11, 1, 100, 50, 0)),
    ("001FF400", "00 11 01 02 00 00 00 00", Grant(0x11, 1, 0x02)),
    ("001FF500", "00 12 02 01 00 11 01 80", Refuse(0x12, 2, 1, 0x11, 384)),
]


def _can_section() -> str:
    text = DOC.read_text(encoding="utf-8")
    start = text.index("\n## CAN (classic CAN 2.0B")
    return text[start : text.index("\n## TCP/IP framing", start)]


def test_examples_cover_every_example_row_of_the_document() -> None:
    rows = re.findall(r"^\| `([0-9A-F]{8})` \| (`[0-9a-f ]+`|-) \|", _can_section(), re.M)
    in_doc = {(ident, data.strip("`")) for ident, data in rows}
    transcribed = {(ident, data) for ident, data, _ in EXAMPLES}
    assert in_doc == transcribed


@pytest.mark.parametrize(("identifier", "data", "frame"), EXAMPLES)
def test_example_row_matches_the_tables(identifier: str, data: str, frame: Frame) -> None:
    raw = b"" if data == "-" else bytes.fromhex(data)
    assert decode_id(int(identifier, 16), raw) == frame
    assert encode(frame) == (int(identifier, 16), raw)


def test_channel_uid_examples() -> None:
    assert name_to_uid("speed") == SPEED == 0xBBCCB9C002D5ED59
    assert name_to_uid("robot/speed") == 0xEB79DAB9BBB48DC7
