"""docs/jaus.md must stay true: its worked examples, refused datagrams, payloads, scaled
integers, message codes and constants are checked against the jaus codec."""

from __future__ import annotations

import random
import re
from pathlib import Path
from typing import Any

import pytest

from ups import jaus
from ups.jaus import JausDecodeError, MessageCode, Reassembler
from ups.jaus._judp import MIN_DATA_SIZE
from ups.jaus._ra33 import RA33_MAX_DATA_SIZE
from ups.jaus._reassembly import DEFAULT_TIMEOUT, MAX_MESSAGE_BYTES, MAX_PARTS, MAX_PENDING_BYTES

DOC = (Path(__file__).resolve().parent.parent / "docs" / "jaus.md").read_text()


def section(title: str) -> str:
    """The text under heading ``title`` up to the next heading of any level."""
    text = DOC.split(f"\n{title}\n", 1)[1]
    return re.split(r"\n#{2,3} ", text, maxsplit=1)[0]


def evaluate(expression: str) -> Any:
    return eval(expression, {"__builtins__": {}}, vars(jaus))  # our own doc, our names


EXAMPLE = re.compile(r"^\| `([0-9a-f ]+)` \| `(.+)` \|$", re.M)
JUDP_EXAMPLES = EXAMPLE.findall(section("### Worked examples (JUDP)"))
RA33_EXAMPLES = EXAMPLE.findall(section("### Worked examples (RA 3.3)"))


def test_the_examples_are_found() -> None:
    assert len(JUDP_EXAMPLES) == 7 and len(RA33_EXAMPLES) == 3


@pytest.mark.parametrize(("raw", "expression"), JUDP_EXAMPLES)
def test_judp_example(raw: str, expression: str) -> None:
    datagram, messages = bytes.fromhex(raw), evaluate(expression)
    assert jaus.encode_judp(messages) == datagram
    assert jaus.decode_judp(datagram) == messages


@pytest.mark.parametrize(("raw", "expression"), RA33_EXAMPLES)
def test_ra33_example(raw: str, expression: str) -> None:
    datagram, message = bytes.fromhex(raw), evaluate(expression)
    assert jaus.encode_ra33(message) == datagram
    assert jaus.decode_ra33(datagram) == message


SPLIT = re.compile(r"^\| `(split_message\(.+\))` \| ((?:`[0-9a-f ]+`(?:, )?)+) \|$", re.M)
SPLITS = SPLIT.findall(section("### A large message, split and rebuilt"))


def test_the_split_example() -> None:
    assert len(SPLITS) == 1
    expression, datagrams = SPLITS[0]
    parts = evaluate(expression)
    expected = [bytes.fromhex(d) for d in re.findall(r"`([0-9a-f ]+)`", datagrams)]
    assert [jaus.encode_judp([p]) for p in parts] == expected
    first = parts[0]
    header = jaus.JudpHeader(first.header.destination, first.header.source, sequence=100)
    whole = jaus.JudpMessage(header, first.code, b"".join(p.payload for p in parts))
    for seed in range(6):
        order = expected[:]
        random.Random(seed).shuffle(order)
        r = Reassembler()
        got = [r.feed(jaus.decode_judp(d)[0], 0.0) for d in order]
        assert [m for m in got if m is not None] == [whole]


REFUSED = re.compile(r"^\| (judp|ra33) \| `([0-9a-f ]+)` \| (.+) \|$", re.M)
REFUSALS = REFUSED.findall(section("## Datagrams the decoders refuse"))


def test_the_refusals_are_found() -> None:
    assert len(REFUSALS) == 21


@pytest.mark.parametrize(("decoder", "raw", "why"), REFUSALS)
def test_refused_datagram(decoder: str, raw: str, why: str) -> None:
    decode = jaus.decode_judp if decoder == "judp" else jaus.decode_ra33
    with pytest.raises(JausDecodeError):
        decode(bytes.fromhex(raw))


def test_empty_datagrams_are_refused() -> None:
    for decode in (jaus.decode_judp, jaus.decode_ra33):
        with pytest.raises(JausDecodeError):
            decode(b"")


PAYLOAD = re.compile(r"^\| `0x([0-9A-F]{4})` \| `([0-9a-f -]+)` \| `(.+)` \|$", re.M)
PAYLOADS = PAYLOAD.findall(section("### Worked examples (payloads)"))


def test_the_payload_examples_are_found() -> None:
    assert len(PAYLOADS) == 25


@pytest.mark.parametrize(("code", "raw", "expression"), PAYLOADS)
def test_payload_example(code: str, raw: str, expression: str) -> None:
    data = b"" if raw == "-" else bytes.fromhex(raw)
    assert jaus.encode_payload(evaluate(expression)) == (int(code, 16), data)
    decoded = jaus.decode_payload(int(code, 16), data)
    assert decoded is not None and jaus.encode_payload(decoded) == (int(code, 16), data)


RA33_PAYLOADS = PAYLOAD.findall(section("### RA 3.3 payloads"))


def test_the_ra33_payload_examples_are_found() -> None:
    assert len(RA33_PAYLOADS) == 4


@pytest.mark.parametrize(("code", "raw", "expression"), RA33_PAYLOADS)
def test_ra33_payload_example(code: str, raw: str, expression: str) -> None:
    data = b"" if raw == "-" else bytes.fromhex(raw)
    assert jaus.encode_ra33_payload(evaluate(expression)) == (int(code, 16), data)
    decoded = jaus.decode_ra33_payload(int(code, 16), data)
    assert decoded is not None and jaus.encode_ra33_payload(decoded) == (int(code, 16), data)


SCALED = re.compile(r"^\| (-?[\d.]+) \| (-?[\d.]+) \| (-?[\d.]+) \| (\d+) \| (\d+) \|$", re.M)
SCALED_ROWS = SCALED.findall(section("## Scaled integers"))


def test_scaled_rows() -> None:
    assert len(SCALED_ROWS) == 9
    for value, lower, upper, bits, integer in SCALED_ROWS:
        assert jaus.to_scaled(float(value), float(lower), float(upper), int(bits)) == int(integer)


CODE_ROW = re.compile(r"^\| `0x([0-9A-F]{4})` \| ([A-Za-z ]+) \| [^|]+ \| ([a-z, ]+) \|$", re.M)
CODES = CODE_ROW.findall(section("## Message codes"))


def test_the_code_table_is_the_codec_table() -> None:
    assert len(CODES) == len(MessageCode)
    assert {int(code, 16) for code, _, _ in CODES} == {int(m) for m in MessageCode}
    for code, name, _ in CODES:
        assert jaus.message_name(int(code, 16)) == name


def test_documented_constants() -> None:
    judp = section("## JUDP (AS5669A)")
    assert "**UDP port 3794**" in judp and jaus.JUDP_PORT == 3794
    assert "`0x02` for AS5669A" in judp and jaus.JUDP_VERSION == 2
    assert "**data size = 14 + n**" in section("### One message") and MIN_DATA_SIZE == 14
    assert "`DEFAULT_PART_SIZE` = 4079" in DOC and jaus.DEFAULT_PART_SIZE == 4079
    assert "at most 4080" in DOC and RA33_MAX_DATA_SIZE == 4080
    assert jaus.RA33_PREFIX == b"JAUS01.0"
    bounds = section("## Reassembly")
    assert "| `DEFAULT_TIMEOUT` | 10 s |" in bounds and DEFAULT_TIMEOUT == 10.0
    assert "| `MAX_PARTS` | 100 |" in bounds and MAX_PARTS == 100
    assert "| `MAX_PENDING_BYTES` | 1 MiB |" in bounds and MAX_PENDING_BYTES == 1 << 20
    assert "| `MAX_MESSAGE_BYTES` | 1 MiB |" in bounds and MAX_MESSAGE_BYTES == 1 << 20
    counts = jaus.ReassemblyCounts()
    for reason in ("expired", "evicted", "duplicate", "conflicting", "oversized", "mismatched"):
        assert f"**{reason}**" in bounds and getattr(counts, reason) == 0


def test_the_hosts_documented_bounds_are_the_codes() -> None:
    from ups.jaus._access import CONTROL_TIMEOUT, MAX_EMERGENCIES, NOTE_EVERY
    from ups.jaus._events import EVENT_TIMEOUT, MAX_EVENTS, MAX_RATE
    from ups.jaus._host import CLIENT_TIMEOUT, MAX_CLIENTS
    from ups.jaus._waypoint_list import DEFAULT_TOLERANCE, MAX_ELEMENTS

    bounds = section("## `ups jaus`: the component host")
    for row, value in (
        ("| `MAX_CLIENTS` | 64 clients |", MAX_CLIENTS == 64),
        ("| `CLIENT_TIMEOUT` | 60 s |", CLIENT_TIMEOUT == 60.0),
        ("| `CONTROL_TIMEOUT` | 5 s |", CONTROL_TIMEOUT == 5.0),
        ("| `MAX_EVENTS` | 64 events, all clients |", MAX_EVENTS == 64),
        ("| `EVENT_TIMEOUT` | 60 s |", EVENT_TIMEOUT == 60.0),
        ("`MAX_RATE` 25 Hz", MAX_RATE == 25.0),
        ("| `MAX_EMERGENCIES` | 16 clients |", MAX_EMERGENCIES == 16),
        ("| `MAX_ELEMENTS` | 256 waypoints |", MAX_ELEMENTS == 256),
        ("tolerance (else 1 m)", DEFAULT_TOLERANCE == 1.0),
    ):
        assert row in bounds and value, row
    rules = " ".join(section("### Control, authority and addresses").split())
    for text, value in (
        ("at most one line per 10 s, `NOTE_EVERY`", NOTE_EVERY == 10.0),
        ("falls silent for 5 s (`CONTROL_TIMEOUT`)", CONTROL_TIMEOUT == 5.0),
        ("at most 16 clients at once, `MAX_EMERGENCIES`", MAX_EMERGENCIES == 16),
    ):
        assert text in rules and value, text


def test_the_mapping_shown_is_the_demo_robots() -> None:
    """Each paragraph of the TOML shown is verbatim in examples/robot.jaus.toml, and the
    demo's mapping loads."""
    from ups.jaus._mapping import load_mapping

    path = Path(__file__).resolve().parent.parent / "examples" / "robot.jaus.toml"
    text = section("## The mapping file: JAUS messages onto UPS channels")
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    assert len(blocks) == 3  # Global Pose, Set Travel Speed, [authority]
    mapping = path.read_text()
    for paragraph in "\n\n".join(blocks).split("\n\n"):
        assert paragraph.strip() and paragraph.strip() + "\n" in mapping, paragraph
    bridge = load_mapping(path)
    assert {"ReportGlobalPose", "SetTravelSpeed"} <= set(bridge)
    assert bridge.authority is not None and bridge.authority.cap("127.0.0.1") is not None
