"""Events larger than one frame across processes: ``ups pub`` and ``ups sub`` on CAN and on
TCP/IP, through ``ups gateway`` both ways, on a classic and on a CAN FD bus.

The CAN side is udp_multicast inside a private network namespace, and SocketCAN vcan0 inside
User-Mode Linux. A raw python-can listener checks what went on the wire.
"""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from ups import _canproto as p
from ups import _cantransfer as t
from ups._canlink import open_bus
from upscli._pubsub import EXIT_LOST

from .procs import Proc, private_multicast_bus, start_tcp_broker, vcan_bus
from .test_gateway_processes import forwarding, start_gateway
from .test_tcp_processes import wait_until

SIZES = (8, 9, 64, 1024, 4096)


def pattern(size: int) -> bytes:
    return bytes((i * 37 + size) & 0xFF for i in range(size))


def publish(channel: str, data: bytes, *network: str) -> None:
    with Proc("pub", channel, data.hex(), *network, "--count", "1") as pub:
        code, _ = pub.finish(timeout=90)
        assert code == 0, pub.stderr_lines


def warm(proc: Proc) -> int:
    """How many of the events ``proc`` printed are empty (a warm-up's)."""
    return sum(1 for line in proc.stdout_lines if json.loads(line)["data"] == "")


def received(proc: Proc) -> list[bytes]:
    try:
        code, out = proc.finish(timeout=90)
    except AssertionError:
        raise AssertionError(f"got only {proc.stdout_lines}") from None
    assert code == 0, (out, proc.stderr_lines)
    return [bytes.fromhex(json.loads(line)["data"]) for line in out.splitlines()]


@pytest.mark.timeout(240)
@pytest.mark.parametrize(
    ("where", "kind"),
    [
        pytest.param("udp_multicast", "classic", marks=pytest.mark.netns),
        pytest.param("udp_multicast", "fd", marks=pytest.mark.netns),
        pytest.param("socketcan", "fd", marks=pytest.mark.socketcan),  # classic: other tests'
    ],
)
def test_large_events_through_the_gateway_both_ways(where: str, kind: str, tmp_path: Path) -> None:
    mbus = private_multicast_bus() if where == "udp_multicast" else vcan_bus()
    fd = kind == "fd"
    bus = mbus + (",fd=True" if fd else "")
    wire = open_bus(bus)
    broker, address = start_tcp_broker("--recovery", "0")
    gw, gw_address = start_gateway(bus, address, tmp_path / "gw.db")
    count = str(len(SIZES))
    try:
        with (
            broker,
            gw,
            Proc("sub", "down", "--can", bus, "--json", "--count", count, "--timeout", "120",
                 "--node-id", "0xC2") as can_sub,
            Proc("sub", "up", "--broker", address, "--json", "--timeout", "120") as tcp_sub,
        ):  # fmt: skip
            can_sub.wait_for_line("subscribed to")
            tcp_sub.wait_for_line("subscribed to")
            wait_until(lambda: forwarding(gw_address, "down", "can"), timeout=30)
            for size in SIZES:  # TCP/IP -> CAN
                publish("down", pattern(size), "--broker", address)
            assert received(can_sub) == [pattern(n) for n in SIZES]
            # CAN -> TCP/IP: the gateway forwards a CAN publisher's channel once it learnt
            # that a TCP node subscribes; warm the channel up until it does
            with Proc("pub", "up", "", "--can", bus, "--count", "100", "--rate", "10",
                      "--node-id", "0xC1"):  # fmt: skip
                wait_until(lambda: len(tcp_sub.stdout_lines) > 0, timeout=30)
            for size in SIZES:
                publish("up", pattern(size), "--can", bus, "--node-id", "0xC1")
            wait_until(lambda: len(tcp_sub.stdout_lines) >= 5 + warm(tcp_sub), timeout=60)
            tcp_sub.stop()
            events = [bytes.fromhex(json.loads(x)["data"]) for x in tcp_sub.stdout_lines]
            assert [e for e in events if e] == [pattern(n) for n in SIZES]
        frames = []
        while (frame := wire.recv(0.2)) is not None:
            if not p.is_management(frame.arbitration_id):
                frames.append(frame)
        large = [f for f in frames if f.arbitration_id & p.ETAG_MASK >= p.LARGE_FIRST_ETAG]
        mtu = 64 if fd else 8
        # the events above 8 bytes went as transfers (a listener read only at the end may have
        # lost some of the thousands of frames from its socket's buffer: no count here)
        assert large
        assert all(f.is_fd == fd for f in large)
        assert max(len(f.data) for f in large) == mtu
    finally:
        wire.shutdown()


@pytest.mark.timeout(240)
def test_two_publisher_processes_interleave_large_events(mbus: str, tmp_path: Path) -> None:
    """Two CAN publishers at once on one channel: their transfers interleave on the bus, and a
    subscriber gets every event of both, whole. (About 4600 frames/s: what a 1 Mbit/s bus
    carries; faster, a slow reader's socket buffer overflows and the loss is only counted.)"""
    with (
        Proc("can-broker", "--can", mbus, "--db", str(tmp_path / "ecb.db"),
             "--recovery", "0.2") as ecb,
        Proc("sub", "shared", "--can", mbus, "--json", "--count", "40", "--timeout", "120",
             "--node-id", "0xD0") as sub,
    ):  # fmt: skip
        ecb.wait_for_line("CAN-ECB")
        sub.wait_for_line("subscribed to")
        a, b = bytes([0xAA]) * 700, bytes([0xBB]) * 900
        with (
            Proc("pub", "shared", a.hex(), "--can", mbus, "--count", "20", "--rate", "20",
                 "--node-id", "0xD1") as pub_a,
            Proc("pub", "shared", b.hex(), "--can", mbus, "--count", "20", "--rate", "20",
                 "--node-id", "0xD2") as pub_b,
        ):  # fmt: skip
            assert pub_a.finish(timeout=90)[0] == 0
            assert pub_b.finish(timeout=90)[0] == 0
        got = received(sub)
        assert sorted(got) == sorted([a] * 20 + [b] * 20)


@pytest.mark.timeout(240)
def test_a_frame_dropped_on_the_wire_is_a_counted_loss(mbus: str, tmp_path: Path) -> None:
    """A raw writer sends transfers with one frame left out: the subscriber process never
    prints a wrong event, and counts the loss (its stats on exit)."""
    raw = open_bus(mbus)
    try:
        with (
            Proc("can-broker", "--can", mbus, "--db", str(tmp_path / "ecb.db"),
             "--recovery", "0.2") as ecb,
            Proc("sub", "lossy", "--can", mbus, "--json", "--count", "2", "--timeout", "120",
                 "--node-id", "0xE0") as sub,
        ):  # fmt: skip
            ecb.wait_for_line("CAN-ECB")
            sub.wait_for_line("subscribed to")
            publish("lossy", bytes(200), "--can", mbus, "--node-id", "0xE1")  # class 2, once
            frame = None
            while (frame := raw.recv(5)) is not None:  # the publisher's transfer: its id
                if frame.arbitration_id & p.ETAG_MASK >= p.LARGE_FIRST_ETAG and not (
                    p.is_management(frame.arbitration_id)
                ):
                    break
            assert frame is not None
            can_id = frame.arbitration_id
            event = pattern(500)
            frames = t.segment(event, 9, 8)
            for data in frames[:10] + frames[11:]:  # frame 10 lost
                raw.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))
            for data in t.segment(event, 10, 8):  # then the same event, intact
                raw.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))
            code, out = sub.finish(timeout=90)
            assert [bytes.fromhex(json.loads(x)["data"]) for x in out.splitlines()] == [
                bytes(200),
                event,
            ]  # never the broken one
            assert code == EXIT_LOST
            assert "lost 1 events" in "\n".join(sub.stderr_lines)
    finally:
        raw.shutdown()


@pytest.mark.netns
@pytest.mark.timeout(240)
def test_a_classic_bus_and_an_fd_bus_meet_through_tcp(tmp_path: Path) -> None:
    """A 3000-byte event from a classic bus reaches a subscriber on a CAN FD bus (8-byte frames
    on one, 64-byte frames on the other), and one from the FD bus the classic one."""
    classic, fd = private_multicast_bus(), private_multicast_bus() + ",fd=True"
    broker, address = start_tcp_broker("--recovery", "0")
    gw_a, gw_a_address = start_gateway(classic, address, tmp_path / "a.db", node_id=0x6A)
    gw_b, gw_b_address = start_gateway(fd, address, tmp_path / "b.db", node_id=0x6B)
    to_fd, to_classic = pattern(3000), pattern(2999)
    with (
        broker,
        gw_a,
        gw_b,
        Proc("sub", "to-fd", "--can", fd, "--json", "--timeout", "120",
             "--node-id", "0xB1") as sub_fd,
        Proc("sub", "to-classic", "--can", classic, "--json", "--timeout", "120",
             "--node-id", "0xA1") as sub_classic,
    ):  # fmt: skip
        for sub in (sub_fd, sub_classic):
            sub.wait_for_line("subscribed to")
        wait_until(lambda: forwarding(gw_b_address, "to-fd", "can"), timeout=30)
        wait_until(lambda: forwarding(gw_a_address, "to-classic", "can"), timeout=30)
        for channel, data, bus, node in (("to-fd", to_fd, classic, "0xA2"),
                                         ("to-classic", to_classic, fd, "0xB2")):  # fmt: skip
            with Proc("pub", channel, data.hex(), "--can", bus, "--count", "200", "--rate", "10",
                      "--node-id", node):  # fmt: skip  # until the gateways forward it
                wait_until(lambda s=channel: bool(lines_of(sub_fd if s == "to-fd" else
                                                           sub_classic)), timeout=60)  # fmt: skip
        for sub, data in ((sub_fd, to_fd), (sub_classic, to_classic)):
            sub.stop()
            assert set(lines_of(sub)) == {data}


def lines_of(proc: Proc) -> list[bytes]:
    return [bytes.fromhex(json.loads(line)["data"]) for line in proc.stdout_lines]
