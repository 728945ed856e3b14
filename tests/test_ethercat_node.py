"""``ups ethercat --ifname IF --map FILE``, the EtherCAT master on a UPS node, as a process
against the tests' slave emulator (tests/ecat, its own process) across a veth pair inside the
private namespace of scripts/netns-run, with examples/robot.ethercat.toml: a UPS event reaches
the slaves' outputs with the exact bytes, the slaves' inputs come back as UPS events on TCP/IP
and on CAN, outputs fall back to their safe values when their channel goes silent, a slave
unplugged mid-run is counted, reported and brought back to OP, and a wrong identity refuses to
start."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import re
import shutil
import struct
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from ups import Node, Subscription
from ups.ethercat._bridge import STATUS_FIELDS, STATUS_LAYOUT

from .ecat_procs import SLAVES, Control, emulator, veth_pair
from .procs import Proc, private_multicast_bus, start_tcp_broker

pytestmark = [pytest.mark.netns, pytest.mark.timeout(180)]

EXAMPLES = Path(__file__).parent.parent / "examples"
MAP = EXAMPLES / "robot.ethercat.toml"
ENV = {"UPS_CATALOG": str(EXAMPLES / "robots.toml")}


@contextlib.contextmanager
def segment(tmp_path: Path, *slaves: str, watchdog: float = 0.0) -> Iterator[
        tuple[str, str, Proc, Control]]:  # fmt: skip
    """(master's interface, slaves' interface, the emulator, its control socket)."""
    ctl = tmp_path / "ctl"
    with (
        veth_pair() as (master, wire),
        emulator(wire, *(slaves or SLAVES), control=ctl, watchdog=watchdog) as emu,
    ):
        control = Control(ctl)
        try:
            yield master, wire, emu, control
        finally:
            control.close()


@contextlib.contextmanager
def ethercat(ifname: str, *network: str) -> Iterator[tuple[Proc, str | None]]:
    """``ups ethercat`` on ``ifname``, its slaves in OP; and its node's address (TCP)."""
    with Proc("ethercat", "--ifname", ifname, "--map", str(MAP), *network, env=ENV) as proc:
        line = proc.wait_for_line(r"master of 2 slave\(s\) on", timeout=60)
        found = re.search(r"ups status (\S+)", line)
        yield proc, found.group(1) if found else None


@dataclass
class Rig:
    """A TCP-ECB, the emulated slaves and ``ups ethercat`` serving them on TCP/IP."""

    broker: str  #: the TCP-ECB's address
    master: str  #: the master's interface
    wire: str  #: the slaves' interface
    emu: Proc
    control: Control
    proc: Proc  #: ups ethercat
    status: str  #: its node's address, for ``ups status``


@contextlib.contextmanager
def over_tcp(tmp_path: Path, watchdog: float = 0.0) -> Iterator[Rig]:
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        segment(tmp_path, watchdog=watchdog) as (master, wire, emu, control),
        ethercat(master, "--broker", address) as (proc, status),
    ):
        assert status is not None
        yield Rig(address, master, wire, emu, control, proc, status)


async def line(proc: Proc, pattern: str, timeout: float = 20.0) -> str:
    return await asyncio.to_thread(proc.wait_for_line, pattern, timeout, stdout=True)


async def lines(proc: Proc, *patterns: str, timeout: float = 20.0) -> None:
    """Wait until each of ``patterns`` matched a stdout line, in any order: what two slaves
    do in the same cycle, or two outputs whose timeouts end in one, comes in either order."""
    waiting = [re.compile(pattern) for pattern in patterns]
    deadline = asyncio.get_running_loop().time() + timeout
    while waiting:
        left = deadline - asyncio.get_running_loop().time()
        try:
            got = await line(proc, "|".join(f"(?:{r.pattern})" for r in waiting), max(0.0, left))
        except AssertionError:
            recent = proc.stdout_lines[-10:]
            raise AssertionError(
                f"no line matching {[r.pattern for r in waiting]}; last {recent}"
            ) from None
        waiting = [r for r in waiting if not r.search(got)]


async def event(sub: Subscription, data: bytes, timeout: float = 10.0) -> None:
    """Wait for an event carrying ``data`` (inputs published every K cycles come meanwhile)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    seen: set[bytes] = set()
    while loop.time() < deadline:
        with contextlib.suppress(TimeoutError):
            msg = await sub.get_msg(timeout=max(0.01, deadline - loop.time()))
            if msg.data == data:
                return
            seen.add(msg.data)
    raise AssertionError(f"no event {data.hex()} on {sub}; seen {sorted(d.hex() for d in seen)}")


async def set_link(ifname: str, state: str) -> None:
    await asyncio.to_thread(subprocess.run, ["ip", "link", "set", ifname, state], check=True)


async def status_of(address: str) -> dict[str, int]:
    code, out = await asyncio.to_thread(Proc("status", address, "--json").finish, 30)
    assert code == 0, out
    return dict(json.loads(out)["ethercat"])


async def outputs_and_inputs(node: Node, emu: Proc, control: Control) -> None:
    """What every network must carry: events -> outputs, inputs -> events."""
    distance = await node.subscribe("robot/distance")
    speed = await node.subscribe("robot/speed")
    await node.publish("robot/max-speed", struct.pack(">h", 123))  # cm/s, big-endian
    await line(emu, r"^outputs 2 ce04$")  # 1230 mm/s, little-endian: exact bytes
    await node.publish("robot/brake", b"\x00")
    await line(emu, r"^outputs 1 00000000$")  # released
    await asyncio.to_thread(control.inputs, 1, "d2040000")  # 1234 cm
    await event(distance, struct.pack(">H", 1234))
    await asyncio.to_thread(control.inputs, 2, "b80b00000000")  # 3000 mm/s
    await event(speed, struct.pack(">h", 300))


async def test_tcp_events_drive_the_outputs_inputs_come_back_and_silence_is_safe(
    tmp_path: Path,
) -> None:
    with over_tcp(tmp_path) as rig:
        await line(rig.emu, r"^outputs 1 01000000$")  # the brake's safe value before any event
        async with Node(broker=rig.broker) as node:
            status = await node.subscribe("ethercat/status")
            await outputs_and_inputs(node, rig.emu, rig.control)
            # the UPS side goes silent: after the map's timeout (0.5 s), the safe values
            await lines(rig.emu, r"^outputs 2 0000$", r"^outputs 1 01000000$")
            msg = await status.get_msg(timeout=5)
            values = dict(zip(STATUS_FIELDS, STATUS_LAYOUT.unpack(msg.data), strict=True))
            assert values["slaves"] == values["in_op"] == 2
            assert values["cycles"] > 0 and values["last_wkc"] == values["expected_wkc"]
        seen = await status_of(rig.status)
        assert seen["silent"] == 2 and seen["in_op"] == 2 and seen["outputs"] == 2
        assert seen["left_op"] == 0, seen  # (lost frames: counted; a busy machine may lose some)
        rig.proc.popen.terminate()  # a daemon asked to stop: the slaves go to INIT, exit 0
        assert (await asyncio.to_thread(rig.proc.finish, 30))[0] == 0
        await lines(rig.emu, r"^state 1 INIT 0x0000$", r"^state 2 INIT 0x0000$")


async def test_can_events_drive_the_outputs_and_inputs_come_back(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    with (
        Proc("can-broker", "--can", bus, "--recovery", "0.2") as ecb,
        segment(tmp_path) as (master, _wire, emu, control),
    ):
        ecb.wait_for_line("CAN-ECB on", timeout=30)
        with ethercat(master, "--can", bus):
            async with Node(can=bus, join_timeout=30) as node:
                await outputs_and_inputs(node, emu, control)


async def test_an_unplugged_slave_is_counted_reported_and_brought_back(tmp_path: Path) -> None:
    """The slaves' link goes down for a second: the frames are lost, the slaves' watchdog
    (0.2 s) takes them to SAFE-OP with an error (0x001B); when the link returns the master
    acknowledges the error and brings them back to OP, and outputs flow again."""
    with over_tcp(tmp_path, watchdog=0.2) as rig:
        await set_link(rig.wire, "down")
        await lines(rig.emu, r"^state 1 SAFE-OP 0x001b$", r"^state 2 SAFE-OP 0x001b$")
        await set_link(rig.wire, "up")
        await lines(rig.emu, r"^state 1 OP 0x0000$", r"^state 2 OP 0x0000$", timeout=30)
        async with Node(broker=rig.broker) as node:
            await node.publish("robot/max-speed", struct.pack(">h", -5))
            await line(rig.emu, r"^outputs 2 ceff$")  # -50 mm/s
        seen = await status_of(rig.status)
        for _ in range(50):  # the master sees them in OP at its next state check (0.1 s)
            if seen["in_op"] == 2:
                break
            seen = await status_of(rig.status)
        assert seen["in_op"] == 2, seen
        assert seen["lost"] > 0 and seen["left_op"] >= 2 and seen["recoveries"] >= 2, seen
        assert "slave 1 is in SAFE-OP+ERROR (0x001b (sync manager watchdog))" in "".join(
            rig.proc.stderr_lines)  # fmt: skip


def test_a_slave_of_another_identity_refuses_to_start(tmp_path: Path) -> None:
    other = SLAVES[1].replace("product=0x1234", "product=0x9999")
    with segment(tmp_path, SLAVES[0], other) as (master, _wire, emu, _control):
        proc = Proc("ethercat", "--ifname", master, "--map", str(MAP), "--broker",
                    "127.0.0.1:9", env=ENV)  # fmt: skip
        code, _ = proc.finish(60)
        assert code == 2
        assert proc.stderr_lines[-1].strip() == (
            "ups ethercat: slave 2 is vendor 0x000005a5 product 0x00009999 revision 0x00000003; "
            "the map expects vendor 0x000005a5 product 0x00001234 (line 21): not starting"
        )
        assert not [ln for ln in emu.stdout_lines if re.match(r"state \d (SAFE-)?OP ", ln)]


def test_tshark_decodes_the_exchange_as_the_emulator_and_the_map_say(tmp_path: Path) -> None:
    """Wireshark's EtherCAT dissector, an independent reading of ETG.1000.4, agrees: every
    frame decodes; each cycle is one LRW of the 16-byte image at logical address 0, its reply
    counted 6 (two slaves, each +1 read, +2 written) and carrying the outputs the map wrote (the
    safe values: brake 1, speed 0) and the inputs the emulator was given."""
    tshark = shutil.which("tshark")
    if tshark is None:
        pytest.skip("tshark is not installed (scripts/setup --test installs it as root)")
    capture = tmp_path / "cycle.pcapng"
    with over_tcp(tmp_path) as rig:
        rig.control.inputs(1, "d2040000")
        rig.control.inputs(2, "b80b00000000")
        sniffing = f"exec {tshark} -i {rig.master} -f 'ether proto 0x88a4' -c 200 -w {capture}"
        with Proc(shell=sniffing, env={}) as sniff:
            assert sniff.finish(60)[0] == 0, "".join(sniff.stderr_lines)
    fields = ["eth.src", "ecat.cmd", "ecat.lad", "ecat.cnt", "ecat.data"]
    decoded = subprocess.run(
        [tshark, "-r", str(capture), "-T", "fields", *(a for f in fields for a in ("-e", f))],
        capture_output=True, text=True, check=True,
    ).stdout.splitlines()  # fmt: skip
    malformed = subprocess.run(
        [tshark, "-r", str(capture), "-Y", "_ws.malformed"], capture_output=True, text=True,
        check=True,
    ).stdout  # fmt: skip
    assert len(decoded) == 200 and not malformed.strip()
    rows = collections.Counter(tuple(line.split("\t")) for line in decoded)
    image = "010000000000" + "d2040000" + "b80b00000000"
    replies = rows[("03:01:01:01:01:01", "0x0c", "0x00000000", "6", image)]
    assert replies >= 50, rows.most_common(4)  # the cycle's reply, once the inputs were set
    lrw_replies = sum(n for (src, cmd, *_), n in rows.items() if src[:2] == "03" and cmd == "0x0c")
    assert lrw_replies - replies <= 1, rows.most_common(6)  # (one may carry the inputs before)
    assert {cmd for _, cmd, *_ in rows} <= {"0x0c", "0x07"}  # LRW, and BRD: the state checks


async def test_a_flood_of_events_does_not_hold_the_cycle_back(tmp_path: Path) -> None:
    """UPS traffic never holds the cycle back: 20,000 events on an output channel as fast as
    TCP takes them (the node's event loop busy throughout) while the slaves' watchdog (0.5 s)
    watches: no slave leaves OP (outputs kept coming), the cycle went on, and the output ends
    with the last event's bytes. (A frame the emulator answers late on a busy machine is
    counted lost: the invariant is progress, not timing.)"""
    with over_tcp(tmp_path, watchdog=0.5) as rig:
        before = await status_of(rig.status)
        async with Node(broker=rig.broker) as node:
            await node.advertise("robot/max-speed")
            for i in range(20_000):
                await node.publish("robot/max-speed", struct.pack(">h", i % 3000))
            await node.publish("robot/max-speed", struct.pack(">h", 3001))
            await line(rig.emu, r"^outputs 2 3a75$")  # 30010 mm/s, little-endian
        after = await status_of(rig.status)
        assert after["outputs"] - before["outputs"] >= 1 and after["cycles"] > before["cycles"]
        assert after["left_op"] == 0 and after["in_op"] == 2, after
        assert not [ln for ln in rig.emu.stdout_lines if "SAFE-OP" in ln and "0x001b" in ln]


async def test_the_jebridge_recipe_a_jaus_ocu_drives_an_ethercat_output(tmp_path: Path) -> None:
    """docs/jaus.md's JEBridge recipe: Set Wrench Effort from a JAUS OCU -> ``ups jaus``
    (examples/robot.jaus.toml) -> robot/max-speed on the robot's CAN bus -> ``ups ethercat``
    (examples/robot.ethercat.toml) -> the drive's output bytes: 25 % -> 50 cm/s -> 500 mm/s."""
    bus = private_multicast_bus()
    with (
        Proc("can-broker", "--can", bus, "--recovery", "0.2") as ecb,
        segment(tmp_path) as (master, _wire, emu, _control),
    ):
        ecb.wait_for_line("CAN-ECB on", timeout=30)
        with (
            ethercat(master, "--can", bus),
            Proc(
                "jaus",
                "--listen",
                "127.0.0.1:0",
                "--map",
                str(EXAMPLES / "robot.jaus.toml"),
                "--can",
                bus,
                env=ENV,
            ) as jaus,  # fmt: skip
        ):
            found = re.search(r"on (\S+) \(JUDP", jaus.wait_for_line(r"JAUS component", 30))
            assert found is not None
            ocu = Proc("jaus-ocu", "--target", found.group(1), "send", "SetWrenchEffort",
                       "propulsive_linear_x=25", "--control")  # fmt: skip
            code, _ = await asyncio.to_thread(ocu.finish, 30)
            assert code == 0, "".join(ocu.stderr_lines)
            await line(emu, r"^outputs 2 f401$")  # 500 mm/s, little-endian
