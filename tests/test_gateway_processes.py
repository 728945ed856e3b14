"""``ups gateway`` with ``ups broker``, ``ups sub`` and ``ups pub`` as separate processes.

The CAN side is udp_multicast inside a private network namespace, and (for the basic path) a
real SocketCAN vcan0 inside User-Mode Linux. A plain python-can listener checks the bus.
"""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path

import can
import pytest

from ups import _canproto as p
from ups import name_to_uid
from ups._canlink import open_bus
from ups._tcpface import query_status

from .procs import Proc, private_multicast_bus, start_tcp_broker
from .test_tcp_processes import wait_until

GW_ID = 0x6A7E


def start_gateway(
    bus: str, broker: str, db: Path, node_id: int = GW_ID, recovery: str = "0.2"
) -> tuple[Proc, str]:
    """``ups gateway``; returns it and the HOST:PORT where ``ups status`` reaches it. Its
    CAN-ECB's recovery window is short (nodes join after it) unless a test relearns in it."""
    gw = Proc(
        "gateway", "--can", bus, "--broker", broker, "--db", str(db), "--node-id", hex(node_id),
        "--recovery", recovery,
    )  # fmt: skip
    try:
        line = gw.wait_for_line(r"gateway .* listening on", timeout=60)
    except BaseException:
        gw.stop()
        raise
    found = re.search(r"listening on (\S+:\d+)", line)
    assert found is not None
    return gw, found.group(1)


def gateway_info(address: str) -> dict:  # type: ignore[type-arg]
    return dict(asyncio.run(query_status(address, timeout=10))["gateway"])


def forwarding(address: str, channel: str, to: str) -> bool:
    return f"0x{name_to_uid(channel):016x}" in gateway_info(address)[f"channels_to_{to}"]


def events_on(bus: can.BusABC, quiet: float = 0.5) -> list[can.Message]:
    """The non-management frames heard until the bus is quiet for ``quiet`` s."""
    frames = []
    while (frame := bus.recv(quiet)) is not None:
        if not p.is_management(frame.arbitration_id):
            frames.append(frame)
    return frames


def event_ids(bus: can.BusABC, count: int) -> set[int]:
    """The identifiers of the next ``count`` non-management frames (5 s at most each)."""
    ids = set()
    for _ in range(count):
        while (frame := bus.recv(5)) is not None and p.is_management(frame.arbitration_id):
            pass
        assert frame is not None, "the bus went quiet"
        ids.add(frame.arbitration_id)
    return ids


def test_can_to_tcp_and_tcp_to_can(mbus: str, wire: can.BusABC, tmp_path: Path) -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    gw, gw_address = start_gateway(mbus, address, tmp_path / "gw.db")
    with broker, gw:
        # CAN publisher -> TCP subscriber, priority kept.
        with Proc(
            "sub", "speed", "--broker", address, "--json", "--count", "3", "--timeout", "60"
        ) as tcp_sub:
            tcp_sub.wait_for_line("subscribed to")
            can_pub = Proc(
                "pub", "speed", "0102", "--can", mbus, "--count", "40", "--rate", "20",
                "--priority", "0x30", "--node-id", "0xC1",
            )  # fmt: skip
            with can_pub:
                code, out = tcp_sub.finish(timeout=60)
                assert code == 0
                events = [json.loads(line) for line in out.splitlines()]
                assert {(e["data"], e["priority"]) for e in events} == {("0102", 0x30)}
                assert {e["source"] for e in events} == {f"0x{GW_ID:016x}"}
                can_pub.stop()
        # TCP publisher -> CAN subscriber, priority kept, the gateway's TxNode on the wire.
        with Proc(
            "sub", "cmd", "--can", mbus, "--json", "--count", "2", "--timeout", "60",
            "--node-id", "0xC2",
        ) as can_sub:  # fmt: skip
            can_sub.wait_for_line("subscribed to")
            wait_until(lambda: forwarding(gw_address, "cmd", "can"), timeout=30)
            events_on(wire, quiet=0.2)  # forget what came before
            with Proc(
                "pub", "cmd", "09", "--broker", address, "--count", "2", "--rate", "20",
                "--priority", "0x40",
            ) as tcp_pub:  # fmt: skip
                assert tcp_pub.finish(timeout=60)[0] == 0
            code, out = can_sub.finish(timeout=60)
            assert code == 0
            events = [json.loads(line) for line in out.splitlines()]
            assert [(e["data"], e["priority"]) for e in events] == [("09", 0x40)] * 2
            txnode = gateway_info(gw_address)["txnode"]
            assert {e["source"] for e in events} == {f"0x{txnode:02x}"}
            ids = {f.arbitration_id for f in events_on(wire) if f.data == b"\x09"}
            assert len(ids) == 1
            (can_id,) = ids
            assert p.split_id(can_id)[:2] == (0x40, txnode)
        info = gateway_info(gw_address)
        assert info["to_can"] == 2 and info["to_tcp"] >= 3 and info["can_dropped"] == 0


@pytest.mark.netns
def test_a_tcp_channel_without_can_subscriber_puts_nothing_on_the_bus(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    wire = open_bus(bus)
    try:
        broker, address = start_tcp_broker("--recovery", "0")
        gw, gw_address = start_gateway(bus, address, tmp_path / "gw.db")
        with broker, gw:
            events_on(wire, quiet=0.2)
            with Proc(
                "pub", "lonely", "01", "--broker", address, "--count", "5", "--rate", "50"
            ) as pub:
                assert pub.finish()[0] == 0
            assert events_on(wire) == []
            assert gateway_info(gw_address)["to_can"] == 0
    finally:
        wire.shutdown()


@pytest.mark.netns
def test_two_buses_two_gateways(tmp_path: Path) -> None:
    bus_a, bus_b = private_multicast_bus(), private_multicast_bus()
    broker, address = start_tcp_broker("--recovery", "0")
    gw_a, gw_a_address = start_gateway(bus_a, address, tmp_path / "a.db", node_id=0x6A)
    gw_b, gw_b_address = start_gateway(bus_b, address, tmp_path / "b.db", node_id=0x6B)
    with broker, gw_a, gw_b:
        sub_a = Proc("sub", "from-b", "--can", bus_a, "--json", "--count", "2", "--node-id", "0xA1")
        sub_b = Proc("sub", "from-a", "--can", bus_b, "--json", "--count", "2", "--node-id", "0xB1")
        host = Proc("sub", "from-a", "from-b", "--broker", address, "--json", "--count", "20")
        with sub_a, sub_b, host:
            for proc in (sub_a, sub_b, host):
                proc.wait_for_line("subscribed to")
            wait_until(lambda: forwarding(gw_a_address, "from-b", "can"), timeout=30)
            wait_until(lambda: forwarding(gw_b_address, "from-a", "can"), timeout=30)
            pub_a = Proc("pub", "from-a", "aa", "--can", bus_a, "--count", "60", "--rate", "20")
            pub_b = Proc("pub", "from-b", "bb", "--can", bus_b, "--count", "60", "--rate", "20")
            with pub_a, pub_b:
                for proc, data in ((sub_a, "bb"), (sub_b, "aa")):
                    code, out = proc.finish(timeout=60)
                    assert code == 0
                    assert {json.loads(line)["data"] for line in out.splitlines()} == {data}
                code, out = host.finish(timeout=60)
                assert code == 0
                seen = {json.loads(line)["data"] for line in out.splitlines()}
                assert seen == {"aa", "bb"}  # a TCP host sees both buses


@pytest.mark.netns
def test_gateway_killed_and_restarted_mid_stream(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    wire = open_bus(bus)
    db = tmp_path / "gw.db"
    broker, address = start_tcp_broker("--recovery", "0")
    first, _ = start_gateway(bus, address, db)
    try:
        with (
            broker,
            first,
            Proc(
                "sub", "speed", "--broker", address, "--json", "--count", "60", "--timeout", "60"
            ) as sub,
        ):
            sub.wait_for_line("subscribed to")
            pub = Proc(
                "pub",
                "speed",
                "01",
                "--can",
                bus,
                "--count",
                "400",
                "--rate",
                "50",
                "--node-id",
                "0xC1",
            )
            with pub:
                wait_until(lambda: len(sub.stdout_lines) >= 10, timeout=30)
                first.kill()
                before = event_ids(wire, 5)
                got = len(sub.stdout_lines)
                second, gw_address = start_gateway(bus, address, db, recovery="2")  # relearns
                with second:
                    code, _ = sub.finish(timeout=60)
                    assert code == 0  # forwarding resumed by itself
                    assert len(sub.stdout_lines) > got
                    after = event_ids(wire, 5)
                    assert before == after and len(after) == 1  # same TxNode, same etag
                    info = gateway_info(gw_address)
                    assert info["can_ecb"]["txnodes"] == 2  # the gateway and pub, no new one
                pub.stop()
    finally:
        wire.shutdown()
