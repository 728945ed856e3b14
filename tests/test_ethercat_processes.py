"""``ups ethercat`` as a process against the tests' slave emulator (tests/ecat, its own
process) across a veth pair inside the private network namespace of scripts/netns-run: ``scan``
finds the slaves and their identities; with no slave it says so; KickCAT, a second and
independent master, brings the same emulated slaves to OP and exchanges process data."""

from __future__ import annotations

import json
import re
import socket
from pathlib import Path

import pytest

from .ecat_procs import SLAVES, emulator, veth_pair
from .procs import Proc

pytestmark = [pytest.mark.netns, pytest.mark.timeout(120)]


def test_scan_finds_the_slaves_and_their_identities() -> None:
    with veth_pair() as (master, wire), emulator(wire, *SLAVES) as slaves:
        code, out = Proc("ethercat", "scan", "--ifname", master, "--json", env={}).finish(60)
        assert code == 0, out
        assert json.loads(out) == [
            {"position": 1, "vendor": 0x2, "product": 0x7D23052, "revision": 0x00110000,
             "name": "EL-test-io", "state": "PRE-OP", "al_status_code": 0, "outputs": 4,
             "inputs": 4},
            {"position": 2, "vendor": 0x5A5, "product": 0x1234, "revision": 3,
             "name": "UPS drive", "state": "PRE-OP", "al_status_code": 0, "outputs": 2,
             "inputs": 6},
        ]  # fmt: skip
        slaves.wait_for_line(r"^state 2 PRE-OP 0x0000$", stdout=True)
        code, out = Proc("ethercat", "scan", "--ifname", master, env={}).finish(60)
        assert code == 0, out
        rows = out.splitlines()
        assert rows[0].split() == ["pos", "vendor", "product", "revision", "state", "out", "in",
                                   "name"]  # fmt: skip
        assert rows[1].split() == ["1", "0x00000002", "0x07d23052", "0x00110000", "PRE-OP",
                                   "4", "4", "EL-test-io"]  # fmt: skip
        assert re.fullmatch(r"\s*2\s+0x000005a5\s+0x00001234\s+0x00000003\s+PRE-OP\s+2\s+6\s+"
                            r"UPS drive", rows[2])  # fmt: skip


def test_scan_without_slaves_or_interface_says_so() -> None:
    with veth_pair() as (master, _wire):
        scan = Proc("ethercat", "scan", "--ifname", master, env={})
        assert scan.finish(60)[0] == 2
        assert scan.stderr_lines[-1].strip() == (
            f"ups ethercat: no EtherCAT slave answers on {master}"
        )
        missing = Proc("ethercat", "scan", "--ifname", "nosuch0", env={})
        assert missing.finish(60)[0] == 2
        assert missing.stderr_lines[-1].startswith("ups ethercat: cannot open nosuch0")


def test_kickcat_brings_the_emulated_slaves_to_op(tmp_path: Path) -> None:
    """An independent master (KickCAT, C++) agrees with the emulator: it finds both slaves,
    maps their process data from the SII, reaches OP; its outputs reach the slaves'
    applications byte for byte and the slaves' inputs come back."""
    kickcat = pytest.importorskip("kickcat")
    control = tmp_path / "ctl"
    with veth_pair() as (master, wire), emulator(wire, *SLAVES, control=control) as slaves:
        ask = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        ask.bind(str(tmp_path / "me"))
        ask.settimeout(10)
        for position, value in ((1, "a1a2a3a4"), (2, "b1b2b3b4b5b6")):
            ask.sendto(f"inputs {position} {value}".encode(), str(control))
            assert ask.recv(4096) == b"ok"
        link = kickcat.create_link(master, "")
        link.set_timeout(0.1)  # s per frame; KickCAT's 2 ms is for a C slave, not a busy Python
        bus = kickcat.Bus(link)
        bus.init(1.0)
        assert [(s.address, s.output_size, s.input_size) for s in bus.slaves()] == [
            (1001, 0, 0), (1002, 0, 0)]  # fmt: skip
        bus.create_mapping()
        bus.request_state(kickcat.State.SAFE_OP)
        bus.wait_for_state(kickcat.State.SAFE_OP, 2.0)
        first, second = bus.slaves()
        first.set_output_bytes(bytes.fromhex("01020304"))
        second.set_output_bytes(bytes.fromhex("0506"))
        bus.process_data()
        bus.request_state(kickcat.State.OPERATIONAL)
        bus.wait_for_state(kickcat.State.OPERATIONAL, 2.0, lambda: bus.process_data())
        bus.process_data()
        slaves.wait_for_line(r"^outputs 1 01020304$", stdout=True)
        slaves.wait_for_line(r"^outputs 2 0506$", stdout=True)
        assert bytes(first.input_data) == bytes.fromhex("a1a2a3a4")
        assert bytes(second.input_data) == bytes.fromhex("b1b2b3b4b5b6")
        ask.sendto(b"status 2", str(control))
        status = json.loads(ask.recv(4096))
        assert (status["state"], status["code"], status["chain"]["dropped"]) == ("OP", 0, 0)
        ask.close()
