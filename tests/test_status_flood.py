"""Issue 29, liveness: every daemon answers under floods, with real processes and sockets.

- A burst of StatusRequests to a TCP-ECB that holds 20 nodes of 8192 channels each: no node is
  dropped, a new node registers, ``ups status`` answers within 2 s, the flood is counted and
  logged (a Status is built at most once per ``STATUS_GAP``, at a cost bounded by what it lists).
- A TCP-ECB whose process could not run for longer than its liveness timeout drops no node
  whose frames waited in its sockets meanwhile.
- A burst of StatusRequests to a node's listening port leaves it registered and answering.
- 100 idle links to ``ups can-broker --status`` leave room for ``ups status``, and are counted
  (links that ask, idle and trickle at once: test_port_fairness.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import socket
import time
from pathlib import Path
from typing import Any

import pytest

from ups import Node, _statuspacer, name_to_uid
from ups import _tcpwire as w
from ups._tcpface import HEARTBEAT, query_status
from ups.broker import _status
from ups.broker.tcp_ecb import MAX_CHANNELS

from .procs import Proc, private_multicast_bus, start_tcp_broker

NODES = 20  # registered nodes, each with MAX_CHANNELS channels of its own
FLOOD = 100  # StatusRequests, each on a link of its own

_Asking = tuple[asyncio.StreamReader, asyncio.StreamWriter]


class _RawNode:
    """A node as the TCP-ECB sees it on the wire: Hello, a Subscribe for each of ``uids``, the
    Ping that ends its registration, then a Ping every HEARTBEAT (as every node). It never
    gives up on the ECB, so only the ECB can end its registration: ``closed`` says it did."""

    def __init__(self, node_id: int, uids: list[int]) -> None:
        self.node_id = node_id
        self.uids = uids
        self.registered = asyncio.Event()  # every Subscribe answered
        self.closed = False

    async def run(self, host: str, port: int) -> None:
        reader, writer = await asyncio.open_connection(host, port)
        writer.write(w.encode(w.Hello(self.node_id, f"raw-{self.node_id:x}", "127.0.0.1", 9)))
        writer.write(b"".join(w.encode(w.Subscribe(uid)) for uid in self.uids))
        writer.write(w.encode(w.Ping()))
        pinger = asyncio.create_task(self._ping(writer))
        decoder = w.Decoder(max_frame=w.MAX_BODY)
        answered = 0
        try:
            while data := await reader.read(1 << 16):
                for frame in decoder.feed(data):
                    answered += isinstance(frame, w.Publishers)
                if answered == len(self.uids):
                    self.registered.set()
            self.closed = True
        finally:
            pinger.cancel()
            writer.close()

    async def _ping(self, writer: asyncio.StreamWriter) -> None:
        while True:
            await asyncio.sleep(HEARTBEAT)
            writer.write(w.encode(w.Ping()))


async def _asking(host: str, port: int, requests: int = 1) -> _Asking:
    """A new link on which ``requests`` StatusRequests are written (not read yet)."""
    reader, writer = await asyncio.open_connection(host, port)
    writer.write(w.encode(w.StatusRequest()) * requests)
    await writer.drain()
    return reader, writer


async def _answer(asking: _Asking) -> w.Frame:
    """The first frame that comes back on the link; then the link is closed."""
    reader, writer = asking
    try:
        decoder = w.Decoder(max_frame=w.MAX_BODY)
        while data := await reader.read(1 << 20):
            if frames := decoder.feed(data):
                return frames[0]
        raise AssertionError("closed without an answer")
    finally:
        writer.close()


async def _ask(host: str, port: int) -> w.Frame:
    return await _answer(await _asking(host, port))


async def _stay(node: Node) -> None:
    """Keep ``node`` registered until cancelled, then close it."""
    try:
        await asyncio.Event().wait()
    finally:
        await node.close()


def _ups_status(address: str) -> dict[str, Any]:
    """``ups status ADDRESS --json --timeout 2``: it fails unless the answer comes within 2 s
    of its connecting."""
    proc = Proc("status", address, "--json", "--timeout", "2")
    code, out = proc.finish()
    assert code == 0, "".join(proc.stderr_lines)
    info: dict[str, Any] = json.loads(out)
    return info


async def test_a_status_flood_drops_no_node_and_holds_up_no_registration() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    host, port = address.rsplit(":", 1)
    nodes = [
        _RawNode(0x5100 + i, [(i + 1) << 32 | j for j in range(MAX_CHANNELS)]) for i in range(NODES)
    ]
    with broker:
        running = [asyncio.create_task(node.run(host, int(port))) for node in nodes]
        try:
            async with asyncio.timeout(40):
                await asyncio.gather(*(node.registered.wait() for node in nodes))
            loop = asyncio.get_running_loop()
            start = loop.time()
            flood = [asyncio.create_task(_ask(host, int(port))) for _ in range(FLOOD)]
            asked = asyncio.create_task(asyncio.to_thread(_ups_status, address))
            newcomer = Node(broker=address, node_id=0x5200, join_timeout=4)
            running.append(asyncio.create_task(_stay(newcomer)))
            async with asyncio.timeout(4):  # a registration waits for no Status
                await newcomer.start()
                await newcomer.subscribe("flood/newcomer")
            await asked  # `ups status` was answered within 2 s
            answers = await asyncio.gather(*flood)  # and so was every request of the flood
            elapsed = loop.time() - start
            assert all(isinstance(answer, w.Status) for answer in answers)

            info = await query_status(address, timeout=2)
            stats = info["stats"]
            assert stats["left"] == 0 and not any(node.closed for node in nodes), stats
            assert stats["nodes"] == NODES + 1 and stats["channels"] == NODES * MAX_CHANNELS + 1
            (entry,) = [n for n in info["nodes"] if n["node_id"] == f"0x{0x5200:016x}"]
            assert list(entry["subscribed"]) == [f"0x{name_to_uid('flood/newcomer'):016x}"]
            # the flood is counted, and cost at most one build per STATUS_GAP
            assert stats["status_paced"] >= 1
            assert stats["status_builds"] <= elapsed / _statuspacer.STATUS_GAP + 3, (stats, elapsed)
            await asyncio.to_thread(broker.wait_for_line, "builds its Status at most every", 5)
        finally:
            for task in running:
                task.cancel()
            await asyncio.gather(*running, return_exceptions=True)
            with contextlib.suppress(NameError):  # the flood began: wait for what it started
                await asyncio.gather(asked, *flood, return_exceptions=True)


async def test_a_tcp_ecb_that_could_not_run_drops_no_node_that_kept_talking() -> None:
    broker, address = start_tcp_broker("--recovery", "0", "--liveness", "1")
    with (
        broker,
        Proc("sub", "held/a", "--broker", address) as one,
        Proc("sub", "held/b", "--broker", address) as other,
    ):
        for sub in (one, other):
            await asyncio.to_thread(sub.wait_for_line, "subscribed to")
        broker.pause()  # the ECB cannot run for twice its liveness; the nodes keep pinging
        try:
            await asyncio.sleep(2.0)
        finally:
            broker.resume()
        line = await asyncio.to_thread(broker.wait_for_line, "could not run for|left: silent")
        assert "could not run for" in line, line
        stats = (await query_status(address, timeout=2))["stats"]
        assert stats["left"] == 0 and stats["joined"] == 2 and stats["held_up"] >= 1, stats


async def test_a_status_flood_on_a_nodes_port_leaves_it_registered_and_answering() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    channels = [f"0x{0x77 << 40 | i:x}" for i in range(1, MAX_CHANNELS + 1)]
    with broker, Proc("sub", *channels, "--broker", address, "-v") as sub:
        await asyncio.to_thread(sub.wait_for_line, "subscribed to", 60)
        (node,) = (await query_status(address))["nodes"]
        host, port = node["address"].rsplit(":", 1)
        # 2000 requests, 50 at once on each of 40 links: before, 5 s of work for the node
        flood = await asyncio.gather(*(_asking(host, int(port), 50) for _ in range(40)))
        try:
            mine = await query_status(node["address"], timeout=2)  # answered within 2 s
        finally:
            answers = await asyncio.gather(*map(_answer, flood), return_exceptions=True)
        assert all(isinstance(answer, w.Status) for answer in answers), answers
        assert len(mine["subscribed"]) == MAX_CHANNELS
        stats = (await query_status(address, timeout=2))["stats"]
        assert stats["left"] == 0 and stats["joined"] == 1, stats  # never silent to the ECB
        mine = await query_status(node["address"], timeout=2)
        assert mine["stats"]["reconnects"] == 0 and mine["stats"]["status_paced"] >= 1
        await asyncio.to_thread(sub.wait_for_line, "builds its Status at most every", 5)


@pytest.mark.netns
def test_idle_links_to_a_can_ecbs_status_port_leave_room_for_ups_status(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    with Proc("can-broker", "--can", bus, "--db", str(tmp_path / "ecb.db"), "--recovery",
              "0.2", "--status", "127.0.0.1:0") as ecb:  # fmt: skip
        line = ecb.wait_for_line(r"status on 127\.0\.0\.1:\d+")
        found = re.search(r"status on (127\.0\.0\.1):(\d+)", line)
        assert found is not None
        address = f"{found.group(1)}:{found.group(2)}"
        idle = [socket.create_connection((found.group(1), int(found.group(2))))
                for _ in range(100)]  # fmt: skip
        try:
            stats = _ups_status(address)["stats"]  # answered within 2 s
            # the idle links beyond MAX_LINKS waited in line, and as many idle links let in
            # before them gave way after their turn, for them and for ups status; counted
            assert stats["status_evicted"] >= 100 - _status.MAX_LINKS, stats
            assert stats["status_refused_busy"] == 0
            deadline = time.monotonic() + _status.TURN + _status.READ_TIMEOUT + 10
            for sock in idle:  # and every idle link is closed, its turn and READ_TIMEOUT after
                sock.settimeout(max(0.1, deadline - time.monotonic()))  # it came at most
                assert sock.recv(16) == b""
            ecb.wait_for_line("the status port: closed .* links that held a slot past", 5)
        finally:
            for sock in idle:
                with contextlib.suppress(OSError):
                    sock.close()
