"""``ups ls --broker``: the network's nodes and channels by name, with real processes."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from ups import Node, name_to_uid
from ups.tools.ls import can_listing, render_can

from .can_ecbs import KINDS, READY, can_ecb_proc
from .procs import Proc
from .test_tcp_processes import start_tcp_broker, wait_until


def test_ls_shows_nodes_and_channels_by_name() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        Proc("sub", "robot/speed", "0x1234", "--broker", address) as sub,
        Proc("pub", "robot/speed", "01", "--broker", address, "--count", "1000"),
    ):
        sub.wait_for_line("subscribed to")

        def listed() -> dict:
            ls = Proc("ls", "--broker", address, "--json")
            code, out = ls.finish()
            assert code == 0, ls.stderr_lines
            return json.loads(out)

        wait_until(lambda: any(c["publishers"] for c in listed()["channels"]))
        table = listed()
        by_name = {n["name"]: n for n in table["nodes"]}
        assert set(by_name) == {"ups-sub", "ups-pub"} and by_name["ups-sub"]["connected"]
        channels = {c["name"]: c for c in table["channels"]}
        assert set(channels) == {"robot/speed", None}  # 0x1234 came without a name
        speed = channels["robot/speed"]
        assert speed["publishers"] == [by_name["ups-pub"]["node_id"]]
        assert speed["subscribers"] == [by_name["ups-sub"]["node_id"]]
        ls = Proc("ls", "--broker", address)
        code, out = ls.finish()
        assert code == 0
        row = next(line for line in out.splitlines() if "robot/speed" in line)
        assert row.split()[2:] == ["ups-pub", "ups-sub"]  # uid, name, publishers, subscribers


async def test_ls_of_a_can_bus_reads_the_ecb_tables_and_listens(bus: str, tmp_path: Path) -> None:
    from ups import broker

    db = tmp_path / "ecb.db"
    async with (
        broker.hosted_can_ecb(bus, db, recovery=0.1),
        Node(can=bus, node_id=0xA1) as pub,
        Node(can=bus, node_id=0xB2) as sub_node,
    ):
        await sub_node.subscribe("speed")
        await pub.publish("speed", b"\x01")

        async def keep_publishing() -> None:
            while True:
                await pub.publish("speed", b"\x02")
                await asyncio.sleep(0.01)  # about 100 frames/s, for the listener to count

        task = asyncio.create_task(keep_publishing())
        try:
            table = await asyncio.to_thread(can_listing, bus, str(db), 0.5)
        finally:
            task.cancel()
    nodes = {n["node_id"]: n for n in table["nodes"]}
    assert set(nodes) == {f"0x{0xA1:016x}", f"0x{0xB2:016x}"}
    assert nodes[f"0x{0xA1:016x}"]["heard"] and nodes[f"0x{0xA1:016x}"]["frames_per_s"] > 10
    (speed,) = [c for c in table["channels"] if c["uid"] == f"0x{name_to_uid('speed'):016x}"]
    assert speed["publishers"] == [f"0x{0xA1:016x}"] and speed["frames_per_s"] > 10
    assert "0x00000000000000a1" in render_can(table)


def test_ls_of_a_can_bus_without_its_database_is_one_line(tmp_path: Path) -> None:
    proc = Proc("ls", "--can", "virtual:nobody", "--db", str(tmp_path / "none.db"))
    code, _ = proc.finish()
    assert code == 2 and "no CAN-ECB database at" in "".join(proc.stderr_lines)


def test_ls_rates_counts_events_on_tcp() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        Proc(
            "pub", "robot/speed", "01", "--broker", address, "--count", "100000", "--rate", "200"
        ),  # fmt: skip
    ):

        def listed() -> dict:
            ls = Proc("ls", "--broker", address, "--json", "--rates", "--listen-for", "1")
            code, out = ls.finish()
            assert code == 0, ls.stderr_lines
            return json.loads(out)

        wait_until(lambda: any(c["publishers"] for c in listed()["channels"]))
        (speed,) = listed()["channels"]
        assert speed["name"] == "robot/speed" and speed["events_per_s"] > 50
        ls = Proc("ls", "--broker", address, "--rates", "--listen-for", "0.5")
        assert "EVENTS/S" in ls.finish()[1]


@pytest.mark.netns
@pytest.mark.parametrize("kind", KINDS)
def test_ls_of_a_can_bus_asks_the_can_ecb_for_who_subscribes(tmp_path: Path, kind: str) -> None:
    """Of ``ups can-broker --status`` and of ``ups c-ecb --status``."""
    from .procs import private_multicast_bus

    bus = private_multicast_bus()
    catalog = tmp_path / "c.toml"
    catalog.write_text('[channel."robot/speed"]\n')
    with can_ecb_proc(kind, bus, tmp_path / "ecb.db", "--recovery", "0.2",
                      "--status", "127.0.0.1:0") as ecb:  # fmt: skip
        line = ecb.wait_for_line(r"status on 127\.0\.0\.1:\d+")
        status = line.split("status on ")[1].strip()
        ecb.wait_for_line(READY)
        with (
            Proc("sub", "robot/speed", "--can", bus, "--node-id", "0x5b") as sub,
            Proc(
                "pub",
                "robot/speed",
                "01",
                "--can",
                bus,
                "--node-id",
                "0x5a",
                "--count",
                "100000",
                "--rate",
                "100",
            ),  # fmt: skip
        ):
            sub.wait_for_line("subscribed to")

            def listed() -> dict:
                ls = Proc("ls", "--can", bus, "--ecb", status, "--catalog", str(catalog),
                          "--json", "--listen-for", "0.5")  # fmt: skip
                code, out = ls.finish()
                assert code == 0, ls.stderr_lines
                return json.loads(out)

            wait_until(lambda: any(c["publishers"] for c in listed()["channels"]))
            (speed,) = listed()["channels"]
            assert speed["name"] == "robot/speed" and speed["etag"] == "0x0010"
            assert speed["subscribers"] == [f"0x{0x5B:016x}"]
            assert speed["publishers"] == [f"0x{0x5A:016x}"]
            status_proc = Proc("status", status, "--json")
            code, out = status_proc.finish()
            assert code == 0 and json.loads(out)["stats"]["joined"] >= 2


def test_ls_ecb_of_something_else_is_one_line() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("sub", "x", "--broker", address) as sub:
        sub.wait_for_line("subscribed to")
        ls = Proc("ls", "--can", "virtual:nobody", "--ecb", address, "--listen-for", "0.1")
        code, _ = ls.finish()
        assert code == 2 and len(ls.stderr_lines) == 1
        assert "not a CAN-ECB's status port" in ls.stderr_lines[0]


def test_one_node_and_one_channel_are_said_in_the_singular() -> None:
    from ups.tools import ls

    node = {"node_id": "0x1", "name": "a", "identity": None, "address": "x:1",
            "connected": True, "subscribed": 1, "published": 0}  # fmt: skip
    channel = {"uid": "0x2", "name": "c", "publishers": [], "subscribers": []}
    table = {"total": {"nodes": 1, "channels": 1}, "nodes": [node], "channels": [channel]}
    lines = ls.render(table).splitlines()
    assert "1 node" in lines and "1 channel" in lines
    table["total"] = {"nodes": 2, "channels": 0}
    assert {"2 nodes", "0 channels"} <= set(ls.render(table).splitlines())
