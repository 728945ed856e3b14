"""``ups c-node`` (libups, the C node) as a process beside ``ups can-broker``, ``ups sub``,
``ups pub`` and ``ups gateway``, on udp_multicast inside a private network namespace.

udp_multicast hands every node its own frames back: the C node counts them (own_echo) and
delivers none of them.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from .can_ecbs import KINDS, READY, can_ecb_proc
from .procs import Proc, private_multicast_bus, start_tcp_broker
from .test_gateway_processes import start_gateway
from .test_tcp_processes import wait_until

pytestmark = pytest.mark.netns


def events(proc: Proc) -> list[dict[str, object]]:
    return [json.loads(line) for line in list(proc.stdout_lines) if line.startswith("{")]


def c_node(bus: str, node_id: int, *args: str) -> Proc:
    return Proc("c-node", "--can", bus, "--node-id", hex(node_id), *args)


def can_broker(bus: str, db: Path, kind: str = "python") -> Proc:
    """The bus's CAN-ECB: ``ups can-broker``, or with ``kind`` "c" ``ups c-ecb``."""
    ecb = can_ecb_proc(kind, bus, db, "--recovery", "0.3")
    ecb.wait_for_line(READY, timeout=30)
    return ecb


@pytest.mark.parametrize("ecb", KINDS)
def test_c_node_and_python_tools_on_can(tmp_path: Path, ecb: str) -> None:
    bus = private_multicast_bus()
    with (
        can_broker(bus, tmp_path / "ecb.db", ecb),
        c_node(bus, 0xC1, "--sub", "robot/cmd", "--json") as c_sub,
        Proc("sub", "robot/speed", "--can", bus, "--json", "--count", "3",
             "--timeout", "60", "--node-id", "0x51") as py_sub,
    ):  # fmt: skip
        c_sub.wait_for_line("joined as TxNode", timeout=30)
        py_sub.wait_for_line("subscribed to", timeout=30)
        with c_node(bus, 0xC2, "--pub", "robot/speed=0102", "--count", "3", "--rate",
                    "20") as c_pub:  # fmt: skip
            assert c_pub.finish(timeout=60)[0] == 0
        said = "".join(c_pub.stderr_lines)  # what it did, not only its join (issue 39)
        assert "ups c-node: publishing: robot/speed is etag 0x" in said
        assert "ups c-node: published 3 events on robot/speed" in said
        code, out = py_sub.finish(timeout=60)
        assert code == 0
        got = [json.loads(line) for line in out.splitlines()]
        assert [e["data"] for e in got] == ["0102"] * 3
        assert [e["priority"] for e in got] == [0x80] * 3
        with Proc("pub", "robot/cmd", "0a0b", "--can", bus, "--count", "3", "--rate", "20",
                  "--node-id", "0x52") as py_pub:  # fmt: skip
            assert py_pub.finish(timeout=60)[0] == 0
        wait_until(lambda: len(events(c_sub)) == 3, timeout=30)
        assert {(e["channel"], e["data"]) for e in events(c_sub)} == {("robot/cmd", "0a0b")}
        c_sub.stop()  # SIGTERM: a normal way to stop, and it says what it got
    said = "".join(c_sub.stderr_lines)
    assert "subscribed: robot/cmd is etag 0x" in said and "received 3 events" in said


def test_large_events_both_ways(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    big = bytes(range(200)) * 3
    with (
        can_broker(bus, tmp_path / "ecb.db"),
        c_node(bus, 0xC3, "--sub", "big/in", "--json") as c_sub,
        Proc("sub", "big/out", "--can", bus, "--json", "--count", "2", "--timeout", "60",
             "--node-id", "0x53") as py_sub,
    ):  # fmt: skip
        c_sub.wait_for_line("joined as TxNode", timeout=30)
        py_sub.wait_for_line("subscribed to", timeout=30)
        with c_node(bus, 0xC4, "--pub", f"big/out={big.hex()}", "--count", "2") as c_pub:
            assert c_pub.finish(timeout=60)[0] == 0
        code, out = py_sub.finish(timeout=60)
        assert code == 0 and [json.loads(x)["data"] for x in out.splitlines()] == [big.hex()] * 2
        with Proc("pub", "big/in", big[:500].hex(), "--can", bus, "--count", "2",
                      "--node-id", "0x54") as py_pub:  # fmt: skip
            assert py_pub.finish(timeout=60)[0] == 0
        wait_until(lambda: len(events(c_sub)) == 2, timeout=30)
        assert [e["data"] for e in events(c_sub)] == [big[:500].hex()] * 2


def test_c_node_through_the_gateway_to_tcp(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    broker, address = start_tcp_broker("--recovery", "0")
    gw, _ = start_gateway(bus, address, tmp_path / "gw.db")
    with (
        broker,
        gw,
        Proc("sub", "robot/speed", "--broker", address, "--json", "--count", "3",
             "--timeout", "60") as tcp_sub,
        c_node(bus, 0xC5, "--sub", "robot/cmd", "--json") as c_sub,
    ):  # fmt: skip
        tcp_sub.wait_for_line("subscribed to", timeout=30)
        c_sub.wait_for_line("joined as TxNode", timeout=30)
        with c_node(bus, 0xC6, "--pub", "robot/speed=beef", "--count", "40", "--rate",
                    "20") as c_pub:  # fmt: skip
            code, out = tcp_sub.finish(timeout=60)
            c_pub.stop()
        assert code == 0
        assert {json.loads(x)["data"] for x in out.splitlines()} == {"beef"}

        def delivered() -> bool:  # the gateway forwards once it learned the subscriber
            with Proc("pub", "robot/cmd", "cafe", "--broker", address) as tcp_pub:
                tcp_pub.finish(timeout=60)
            return len(events(c_sub)) > 0

        wait_until(delivered, timeout=30)
        assert {e["data"] for e in events(c_sub)} == {"cafe"}


def test_join_storm_of_c_and_python_nodes(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    c_ids = [0x1000 + i for i in range(4)] + [0xF000_0000_0000_0000 + i for i in range(2)]
    with can_broker(bus, tmp_path / "ecb.db"):
        nodes = [c_node(bus, i, "--sub", "storm", "--json") for i in c_ids]
        nodes += [
            Proc("sub", "storm", "--can", bus, "--json", "--node-id", hex(0x1100 + i))
            for i in range(3)
        ]
        try:
            txnodes = set()
            for proc in nodes[: len(c_ids)]:
                line = proc.wait_for_line("joined as TxNode", timeout=60)
                txnodes.add(line.rsplit(" ", 1)[1])
            for proc in nodes[len(c_ids) :]:
                proc.wait_for_line("subscribed to", timeout=60)
            assert len(txnodes) == len(c_ids)
            with Proc("pub", "storm", "07", "--can", bus, "--node-id", "0x1200") as pub:
                assert pub.finish(timeout=60)[0] == 0
            wait_until(lambda: all(events(n) for n in nodes[: len(c_ids)]), timeout=30)
            for proc in nodes[: len(c_ids)]:
                assert [e["data"] for e in events(proc)] == ["07"]
        finally:
            for proc in nodes:
                proc.stop()


@pytest.mark.parametrize(
    ("keep_db", "ecb"),
    [(True, "python"), (False, "python"), (True, "c")],
    ids=["with-db-python", "lost-db-python", "with-db-c"],
)
def test_can_broker_restarts_no_wrong_delivery(tmp_path: Path, keep_db: bool, ecb: str) -> None:
    bus = private_multicast_bus()
    first = can_broker(bus, tmp_path / "one.db", ecb)
    with c_node(bus, 0xC7, "--sub", "speed", "--json") as c_sub:
        try:
            c_sub.wait_for_line("joined as TxNode", timeout=30)
            for data in ("01", "02"):  # the other channel first, so the etags differ
                with Proc("pub", "other", "ff", "--can", bus, "--node-id", "0x61") as pub:
                    assert pub.finish(timeout=60)[0] == 0
                with Proc("pub", "speed", data, "--can", bus, "--node-id", "0x62") as pub:
                    assert pub.finish(timeout=60)[0] == 0
                wait_until(lambda d=data: d in [e["data"] for e in events(c_sub)], timeout=30)
                first.stop()
                first = can_broker(bus, tmp_path / ("one.db" if keep_db else f"{data}.db"), ecb)
            assert [e["data"] for e in events(c_sub)] == ["01", "02"]
        finally:
            first.stop()
