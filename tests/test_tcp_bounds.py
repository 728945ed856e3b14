"""Bounded resources on TCP/IP: connections that never say Hello, partial frames, too many
connections, too many channels, a status too big to send. The TCP-ECB keeps serving nodes."""

from __future__ import annotations

import asyncio
import contextlib
import resource
import socket
from pathlib import Path

import pytest

from ups import AccessDenied, BrokerUnavailable, Node
from ups._tcpface import query_status
from ups.broker import _tcpstatus, tcp_ecb

from .conftest import eventually
from .procs import start_tcp_broker
from .test_tcp_node import running_tcp_ecb


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def _connect_idle(address: str, count: int) -> list[socket.socket]:
    host, port = address.rsplit(":", 1)
    socks = []
    for _ in range(count):
        s = socket.socket()
        s.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            s.connect((host, int(port)))
        socks.append(s)
    return socks


async def _until_evicted(address: str, count: int) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 20
    while True:
        with contextlib.suppress(BrokerUnavailable):  # the asking connection may be evicted too
            if (await query_status(address, timeout=1))["stats"]["evicted"] >= count:
                return
        assert loop.time() < deadline, f"fewer than {count} idle connections turned away"
        await asyncio.sleep(0.05)


async def test_five_thousand_idle_connections_leave_the_ecb_bounded_and_open() -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 6000:
        pytest.skip(f"the open-file limit ({hard}) is below what this test needs")
    resource.setrlimit(
        resource.RLIMIT_NOFILE, (max(soft, 6000) if hard == resource.RLIM_INFINITY else hard, hard)
    )
    broker, address = start_tcp_broker("--recovery", "0")
    with broker:
        pid = broker.popen.pid
        before = _rss_kib(pid)
        socks = _connect_idle(address, 5000)
        try:
            await _until_evicted(address, 1000)  # it accepts them, and turns most away
            async with Node(broker=address, node_id=0xB1, join_timeout=10) as node:
                sub = await node.subscribe("still/open")  # a node still gets in and is served
                await node.publish("still/open", b"1")
                assert (await sub.get_msg(timeout=5)).data == b"1"
            grown = _rss_kib(pid) - before
            status = await query_status(address)
            stats = status["stats"]
            assert stats["evicted"] >= 1000 and stats["links"] <= 256 + 2, stats
            assert grown < 64 * 1024, f"the TCP-ECB grew by {grown} KiB"
        finally:
            for s in socks:
                s.close()


async def test_a_connection_without_hello_is_closed_and_its_partial_frame_refused() -> None:
    async with running_tcp_ecb(hello_timeout=0.3) as ecb:
        reader, writer = await asyncio.open_connection("127.0.0.1", ecb.port)
        writer.write(bytes([1, 0x10, 0, 0]) + bytes(1000))  # announces 1 MiB before its Hello
        await writer.drain()
        assert await asyncio.wait_for(reader.read(), 5) == b""  # closed at once
        writer.close()
        reader, writer = await asyncio.open_connection("127.0.0.1", ecb.port)  # says nothing
        assert await asyncio.wait_for(reader.read(), 5) == b""  # closed after the timeout
        writer.close()
        await eventually(lambda: ecb.stats()["timed_out"] == 1 and ecb.stats()["links"] == 0)
        assert ecb.counters["malformed"] == 1


async def test_channels_per_node_and_status_size_are_bounded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(tcp_ecb, "MAX_CHANNELS", 40)
    monkeypatch.setattr(_tcpstatus, "STATUS_LIST", 25)
    async with (
        running_tcp_ecb() as ecb,
        Node(broker=f"127.0.0.1:{ecb.port}", node_id=0xB2, join_timeout=5) as node,
    ):
        await node.subscribe(*(f"many/{i}" for i in range(40)))
        with pytest.raises(AccessDenied, match="at most 40 channels"):  # refused, counted
            await node.publish("one/more", b"")
        await eventually(lambda: ecb.stats()["limited"] == 1)
        status = await query_status(f"127.0.0.1:{ecb.port}")
        assert len(status["channels"]) == 25 and status["stats"]["channels"] == 40
        assert status["listed"] == {"nodes": 1, "channels": 25, "at_most": 25}
