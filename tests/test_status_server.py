"""The CAN-ECB's status port: it answers a StatusRequest, ends every other link, and holds
at most MAX_LINKS links at once (the others are closed and counted)."""

from __future__ import annotations

import asyncio

from broker import _status
from broker._status import StatusServer
from ups import _tcpwire as w

from .conftest import eventually


async def test_status_answers_asks_and_bounds_its_links() -> None:
    server = StatusServer("127.0.0.1:0", lambda: {"hello": 1})
    await server.start()
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(w.encode(w.StatusRequest()))
        frames = w.Decoder().feed(await reader.read(1 << 16))
        assert frames == [w.Status({"hello": 1})]
        writer.close()

        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"\xff" * 64)  # not a frame of ours: the link ends, counted
        assert await reader.read() == b""
        writer.close()
        await eventually(lambda: server.counters["bad_requests"] == 1)

        idle = [await asyncio.open_connection("127.0.0.1", server.port)
                for _ in range(_status.MAX_LINKS)]  # fmt: skip
        await eventually(lambda: len(server._links) == _status.MAX_LINKS)
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        assert await reader.read() == b""  # one too many: closed at once
        await eventually(lambda: server.counters["refused_busy"] == 1)
        for _, idle_writer in idle:
            idle_writer.close()
        assert server.counters["answered"] == 1
    finally:
        await server.close()
