"""The CAN-ECB's status port: it answers a StatusRequest, ends every other link, and holds at
most MAX_LINKS links at once: a new one closes the oldest that has not asked yet, and is
closed itself only when every link has asked. Its counters ride in the Status it serves."""

from __future__ import annotations

import asyncio

import pytest

from ups import _tcpwire as w
from ups.broker import _status
from ups.broker._status import StatusServer

from .conftest import eventually


async def _ask(port: int) -> w.Frame:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(w.encode(w.StatusRequest()))
        decoder = w.Decoder()
        while data := await reader.read(1 << 16):
            if frames := decoder.feed(data):
                return frames[0]
        raise AssertionError("closed without an answer")
    finally:
        writer.close()


async def test_status_answers_asks_and_makes_room_for_a_real_request() -> None:
    server = StatusServer("127.0.0.1:0", lambda: {"hello": 1, "stats": {"mine": 2}})
    await server.start()
    try:
        status = await _ask(server.port)
        assert isinstance(status, w.Status) and status.info["hello"] == 1
        assert status.info["stats"]["mine"] == 2  # the daemon's own, and the port's counters
        assert status.info["stats"]["status_evicted"] == 0

        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"\xff" * 64)  # not a frame of ours: the link ends, counted
        assert await reader.read() == b""
        writer.close()
        await eventually(lambda: server.counters["status_bad_requests"] == 1)

        idle = [await asyncio.open_connection("127.0.0.1", server.port)
                for _ in range(_status.MAX_LINKS + 4)]  # fmt: skip
        # the four beyond MAX_LINKS closed the four oldest idle links, not themselves
        await eventually(lambda: server.counters["status_evicted"] == 4)
        assert [await r.read() for r, _ in idle[:4]] == [b""] * 4
        status = await asyncio.wait_for(_ask(server.port), 2)  # room for it: a fifth is closed
        assert isinstance(status, w.Status) and status.info["stats"]["status_evicted"] == 5
        assert server.counters["status_refused_busy"] == 0
        for _, idle_writer in idle:
            idle_writer.close()
        await eventually(lambda: server.counters["status_answers"] == 2)
    finally:
        await server.close()


async def test_a_newcomer_is_refused_only_when_every_link_waits_for_its_answer() -> None:
    server = StatusServer("127.0.0.1:0", lambda: {"hello": 1})
    await server.start()
    try:
        assert isinstance(await _ask(server.port), w.Status)
        server._pacer.gap = 60.0  # the next Status is a minute away: askers wait
        asking = [asyncio.create_task(_ask(server.port)) for _ in range(_status.MAX_LINKS)]
        await eventually(lambda: server.counters["status_paced"] == _status.MAX_LINKS)
        assert server.counters["status_builds"] == 1  # they wait for the next: none built yet
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        assert await reader.read() == b""  # no idle link to close: this one is
        writer.close()
        await eventually(lambda: server.counters["status_refused_busy"] == 1)
        assert server.counters["status_evicted"] == 0
        for task in asking:
            task.cancel()
        await asyncio.gather(*asking, return_exceptions=True)
    finally:
        await server.close()


async def test_an_idle_link_is_closed_after_the_read_timeout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(_status, "READ_TIMEOUT", 0.2)
    server = StatusServer("127.0.0.1:0", lambda: {})
    await server.start()
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        assert await asyncio.wait_for(reader.read(), 5) == b""  # says nothing: closed
        writer.close()
        assert server.counters["status_timed_out"] == 1
    finally:
        await server.close()


async def test_a_status_that_cannot_be_built_ends_the_asking_link_and_the_port_serves_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    calls = 0

    def info() -> dict[str, int]:
        nonlocal calls
        calls += 1
        if calls == 1:
            raise RuntimeError("a bug")
        return {"calls": calls}

    server = StatusServer("127.0.0.1:0", info)
    await server.start()
    try:
        with pytest.raises(AssertionError, match="closed without an answer"):
            await _ask(server.port)
        assert "could not build its Status" in caplog.text
        status = await _ask(server.port)  # the next build, a gap later
        assert isinstance(status, w.Status) and status.info["calls"] == 2
        assert status.info["stats"]["status_bad_requests"] == 1
    finally:
        await server.close()
