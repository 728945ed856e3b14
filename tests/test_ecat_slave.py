"""The tests' EtherCAT slave emulator (tests/ecat) on frames built here from ETG.1000.4, no
network: the working-counter rules of each addressing mode, the SII read through the EEPROM
registers, the AL state machine and its status codes, process data through the FMMUs only in
SAFE-OP and OP. (Against real masters, pysoem and KickCAT: tests/test_ethercat_processes.py.)"""

from __future__ import annotations

import struct

import pytest

from .ecat._chain import Chain
from .ecat._esc import (
    AL_BOOTSTRAP_NOT_SUPPORTED,
    AL_INVALID_OUTPUT_CONFIG,
    AL_INVALID_STATE_CHANGE,
    AL_SM_WATCHDOG,
    APRD,
    APWR,
    BRD,
    BWR,
    FPRD,
    FPWR,
    INIT,
    LRD,
    LRW,
    LWR,
    OP,
    PREOP,
    SAFEOP,
    Slave,
)
from .ecat._sii import INPUT_START, OUTPUT_START, Identity, crc8

HEADER = bytes(6) + b"\x01\x01\x01\x01\x01\x01" + b"\x88\xa4"


def frame(*datagrams: tuple[int, int, int, bytes]) -> bytes:
    """An Ethernet frame of datagrams (command, ADP, ADO, data), index 0x42."""
    body = b""
    for n, (command, adp, ado, data) in enumerate(datagrams):
        more = 0x8000 if n < len(datagrams) - 1 else 0
        body += struct.pack("<BBHHHH", command, 0x42, adp, ado, len(data) | more, 0)
        body += data + b"\x00\x00"
    return HEADER + struct.pack("<H", len(body) | 0x1000) + body


def replies(reply: bytes | None) -> list[tuple[int, bytes, int]]:
    """(ADP, data, WKC) of each datagram of a reply."""
    assert reply is not None
    out, at = [], 16
    while True:
        _cmd, _idx, adp, _ado, size, _irq = struct.unpack_from("<BBHHHH", reply, at)
        data = reply[at + 10 : at + 10 + (size & 0x7FF)]
        (wkc,) = struct.unpack_from("<H", reply, at + 10 + len(data))
        out.append((adp, data, wkc))
        at += 12 + len(data)
        if not size & 0x8000:
            return out


def one(chain: Chain, command: int, adp: int, ado: int, data: bytes) -> tuple[int, bytes, int]:
    (answer,) = replies(chain.process(frame((command, adp, ado, data))))
    return answer


@pytest.fixture
def chain() -> Chain:
    return Chain([
        Slave(Identity(0x2, 0x7D23052, 0x10, "first", outputs=4, inputs=2)),
        Slave(Identity(0x99, 0x5, 0x1, "second", outputs=2, inputs=6)),
    ])  # fmt: skip


def address(chain: Chain) -> None:
    """Station addresses 0x1001, 0x1002 by auto-increment position, as a master sets them."""
    for n in range(2):
        one(chain, APWR, (-n) & 0xFFFF, 0x0010, struct.pack("<H", 0x1001 + n))


def request(chain: Chain, station: int, state: int) -> tuple[int, int]:
    """AL control = ``state``; returns (AL status, AL status code)."""
    assert one(chain, FPWR, station, 0x0120, struct.pack("<H", state))[2] == 1
    _adp, data, _wkc = one(chain, FPRD, station, 0x0130, bytes(6))
    return data[0], struct.unpack_from("<H", data, 4)[0]


def sm(start: int, size: int, control: int) -> bytes:
    return struct.pack("<HHBBBB", start, size, control, 0, 1, 0)


def fmmu(logical: int, size: int, phys: int, kind: int) -> bytes:
    return struct.pack("<IHBBHBBB", logical, size, 0, 7, phys, 0, kind, 1) + bytes(3)


def test_broadcast_counts_every_slave_and_auto_increment_addresses_one(chain: Chain) -> None:
    assert one(chain, BRD, 0, 0x0000, bytes(2)) == (2, b"\x11\x01", 2)  # type, revision
    assert one(chain, BWR, 0, 0x0101, b"\x00")[2] == 2
    assert one(chain, APRD, 0xFFFF, 0x0110, bytes(2)) == (1, struct.pack("<H", 0x0230), 1)
    assert one(chain, APRD, 0x0000, 0x0110, bytes(2)) == (2, struct.pack("<H", 0x0A30), 1)
    assert one(chain, APRD, 0xFFFE, 0x0110, bytes(2))[2] == 0  # no third slave


def test_configured_addresses_and_read_only_registers(chain: Chain) -> None:
    address(chain)
    assert one(chain, FPRD, 0x1002, 0x0010, bytes(2)) == (0x1002, b"\x02\x10", 1)
    assert one(chain, FPRD, 0x1003, 0x0010, bytes(2))[2] == 0
    assert one(chain, FPWR, 0x1001, 0x0130, b"\x08\x00")[2] == 1  # AL status: read-only
    assert chain.slaves[0].state == INIT


def test_the_sii_reads_back_identity_and_name(chain: Chain) -> None:
    address(chain)
    words = {}
    for word in (0x08, 0x0A, 0x0C):
        one(chain, FPWR, 0x1002, 0x0502, struct.pack("<HI", 0x0100, word))
        status = one(chain, FPRD, 0x1002, 0x0502, bytes(2))[1]
        assert struct.unpack("<H", status)[0] & 0x8000 == 0  # not busy
        words[word] = struct.unpack("<I", one(chain, FPRD, 0x1002, 0x0508, bytes(4))[1])[0]
    assert words == {0x08: 0x99, 0x0A: 0x5, 0x0C: 0x1}
    sii = chain.slaves[1].sii
    assert crc8(sii[:14]) == sii[14]
    assert b"\x0a\x00" in sii[0x80:0x84] and b"second" in sii  # the strings category first


def test_al_state_machine_refuses_with_the_codes_and_holds_the_error(chain: Chain) -> None:
    address(chain)
    assert request(chain, 0x1001, OP) == (INIT | 0x10, AL_INVALID_STATE_CHANGE)
    assert request(chain, 0x1001, PREOP) == (INIT | 0x10, AL_INVALID_STATE_CHANGE)  # held
    assert request(chain, 0x1001, PREOP | 0x10) == (PREOP, 0)  # acknowledged
    assert request(chain, 0x1001, 3) == (PREOP | 0x10, AL_BOOTSTRAP_NOT_SUPPORTED)
    assert request(chain, 0x1001, SAFEOP | 0x10) == (PREOP | 0x10, AL_INVALID_OUTPUT_CONFIG)
    one(chain, FPWR, 0x1001, 0x0800, sm(OUTPUT_START, 4, 0x64) + sm(INPUT_START, 2, 0x20))
    assert request(chain, 0x1001, SAFEOP | 0x10) == (SAFEOP, 0)
    assert request(chain, 0x1001, OP) == (OP, 0)
    assert request(chain, 0x1001, INIT) == (INIT, 0)


def bring_up(chain: Chain) -> None:
    """Both slaves to OP with outputs at logical 0 (4 + 2) and inputs at 6 (2 + 6)."""
    address(chain)
    layout = [(0x1001, 4, 2, 0, 6), (0x1002, 2, 6, 4, 8)]
    for station, outputs, inputs, out_at, in_at in layout:
        one(chain, FPWR, station, 0x0800, sm(OUTPUT_START, outputs, 0x64)
            + sm(INPUT_START, inputs, 0x20))  # fmt: skip
        one(chain, FPWR, station, 0x0600, fmmu(out_at, outputs, OUTPUT_START, 2)
            + fmmu(in_at, inputs, INPUT_START, 1))  # fmt: skip
        request(chain, station, PREOP)
    assert one(chain, LRW, 0, 0, bytes(14))[2] == 0  # PRE-OP: no process data
    for station, *_ in layout:
        assert request(chain, station, SAFEOP) == (SAFEOP, 0)


def test_logical_commands_count_read_and_write_per_slave(chain: Chain) -> None:
    bring_up(chain)
    chain.slaves[0].inputs[:] = b"\xaa\xbb"
    chain.slaves[1].inputs[:] = bytes(range(1, 7))
    _adp, data, wkc = one(chain, LRW, 0, 0, bytes(range(0x10, 0x16)) + bytes(8))
    assert wkc == 6  # two slaves, each +1 read, +2 written
    assert data[6:] == b"\xaa\xbb" + bytes(range(1, 7))
    assert chain.slaves[0].outputs == bytes(4)  # SAFE-OP: the application holds safe outputs
    for station in (0x1001, 0x1002):
        request(chain, station, OP)
    assert one(chain, LWR, 0, 0, bytes(range(0x10, 0x16)))[2] == 2
    assert chain.slaves[0].outputs == bytes(range(0x10, 0x14))
    assert chain.slaves[1].outputs == b"\x14\x15"
    assert one(chain, LRD, 6, 0, bytes(8))[1:] == (b"\xaa\xbb" + bytes(range(1, 7)), 2)
    assert one(chain, LRD, 100, 0, bytes(8))[2] == 0  # nobody's logical range
    request(chain, 0x1001, SAFEOP)
    assert chain.slaves[0].outputs == bytes(4)  # out of OP: safe


def test_several_datagrams_in_one_frame(chain: Chain) -> None:
    reply = chain.process(frame((BRD, 0, 0x0130, bytes(2)), (APRD, 0, 0x0000, bytes(1))))
    assert [r[2] for r in replies(reply)] == [2, 1]


def test_malformed_frames_are_counted_and_dropped(chain: Chain) -> None:
    good = frame((BRD, 0, 0x0130, bytes(2)))
    assert chain.process(good[:20]) is None
    assert chain.process(good[:14] + b"\xff\x17" + good[16:]) is None  # longer than the frame
    assert chain.process(good[:12] + b"\x08\x00" + good[14:]) is None  # not EtherCAT
    assert chain.counts["dropped"] == 3


def test_the_watchdog_takes_op_down_to_safe_op(chain: Chain) -> None:
    bring_up(chain)
    slave = chain.slaves[0]
    slave.watchdog = 0.1
    request(chain, 0x1001, OP)
    slave.tick(slave.last_output_write + 0.05)
    assert slave.state == OP
    slave.tick(slave.last_output_write + 0.2)
    assert slave.al_status == (SAFEOP, True, AL_SM_WATCHDOG)
