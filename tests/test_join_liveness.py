"""Joins make progress whatever the load: nodes of one process share one connection, late
answers slow a census down but never stop it, and floods of Knock and Stage frames cost bounded
work, are counted and logged, and joins complete under them (issue: liveness)."""

from __future__ import annotations

import asyncio
import random
import threading
from pathlib import Path

import can
import pytest

from ups import Node
from ups import _canproto as p
from ups._canlink import open_bus
from ups._tcpface import query_status

from .procs import Proc, private_multicast_bus


async def test_nodes_of_one_loop_on_one_bus_share_one_connection(bus: str, ecb: object) -> None:
    """Spelled alike or not, a spec naming the same interface, channel and options is one
    connection; a python-can bus handed over is a connection of its own; the last node to
    close closes the shared one."""
    spelled = f"{bus},receive_own_messages=false"
    other = f"{bus.partition(':')[0]}:{bus.partition(':')[2]}, receive_own_messages = False"
    own = can.Bus(interface="virtual", channel=bus.partition(":")[2])
    nodes = [Node(can=spelled, node_id=1), Node(can=other, node_id=2), Node(can=own, node_id=3)]
    try:
        for node in nodes:
            await node.start()
        a, b, c = (node.face.link for node in nodes)  # type: ignore[attr-defined]
        assert a is b and c is not a
        await nodes[0].close()
        assert not a._closed, "closed under a node still using it"
        await nodes[1].close()
        assert a._closed
    finally:
        for node in nodes:
            await node.close()
        own.shutdown()


@pytest.mark.netns
async def test_sixty_nodes_each_given_the_bus_spec_in_one_process_join(tmp_path: Path) -> None:
    """Each node is given the bus spec, as an application writes it (before, each opened a
    connection of its own and none of 45 joined within 60 s)."""
    bus = private_multicast_bus()
    with Proc("can-broker", "--can", bus, "--db", str(tmp_path / "ecb.db"), "--recovery", "0.2"):
        nodes = [Node(can=bus, node_id=0x5000 + i) for i in range(60)]
        try:
            await asyncio.gather(*(node.start() for node in nodes))
            txnodes = {node.stats()["txnode"] for node in nodes}
            assert txnodes == set(range(60))
        finally:
            for node in nodes:
                await node.close()


class Rogue:
    """A node that answers what it should not: two extra Stage frames (random nibbles, at the
    first stage asked) to every Census and Query, a Knock and a Stage for a random epoch every
    ``gap`` s. Bounded: it stops after ``limit`` frames, or when told."""

    def __init__(self, bus: str, *, gap: float = 0.01, limit: int = 20_000) -> None:
        self._bus = open_bus(bus)
        self._gap = gap
        self._limit = limit
        self._rng = random.Random(7)
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _send(self, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        self._bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))
        self.sent += 1

    def _run(self) -> None:
        rng = self._rng
        while not self._stop.is_set() and self.sent < self._limit:
            frame = self._bus.recv(self._gap)
            if frame is None or not frame.is_extended_id:
                self._send(p.Knock())
                self._send(p.Stage(rng.randrange(p.EPOCHS), rng.randrange(16), rng.randrange(16)))
                continue
            try:
                msg = p.decode(frame.arbitration_id, bytes(frame.data))
            except Exception:
                continue
            if isinstance(msg, p.Census | p.Query):
                first = len(msg.prefix) if isinstance(msg, p.Query) else 0
                for _ in range(2):
                    self._send(p.Stage(msg.epoch, first, rng.randrange(16)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._bus.shutdown()


@pytest.mark.netns
async def test_joins_complete_under_a_flood_of_knocks_and_stage_answers(tmp_path: Path) -> None:
    """Before: one rogue adding two Stage answers to each query made 3 of 3 joiners fail,
    thousands of queries waited, and nothing was counted or logged."""
    bus = private_multicast_bus()
    with Proc(
        "can-broker", "--can", bus, "--db", str(tmp_path / "ecb.db"), "--recovery", "0.2",
        "--status", "127.0.0.1:0",
    ) as ecb:  # fmt: skip
        line = ecb.wait_for_line(r"status on 127\.0\.0\.1:\d+")
        status = line.split("status on ")[1].strip()
        ecb.wait_for_line("CAN-ECB on")
        rogue = Rogue(bus)
        nodes = [Node(can=bus, node_id=random.getrandbits(64)) for _ in range(3)]
        try:
            await asyncio.gather(*(node.start() for node in nodes))
            assert len({node.stats()["txnode"] for node in nodes}) == 3
        finally:
            rogue.close()
            for node in nodes:
                await node.close()
        assert rogue.sent > 100, "the rogue did not get going"
        stats = (await query_status(status, 5.0, None))["stats"]
        assert stats["census_incomplete"] > 0 and stats["census_knocks"] > 0
        assert stats["census_late_stages"] > 0
        ecb.wait_for_line(r"census: .*(incomplete|late)")
