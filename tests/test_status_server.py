"""The CAN-ECB's status port: it answers a StatusRequest, ends every other link, and serves
MAX_LINKS links at once; newcomers wait in line, and a link that has not asked gives way
after its turn (ups/_port.py's rules, in tests/test_port.py). Its counters ride in the
Status it serves."""

from __future__ import annotations

import asyncio
import socket

import pytest

from ups import _tcpwire as w
from ups._errors import ConfigError
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
        # the four beyond MAX_LINKS wait in line; a real request comes after them: after
        # their turn, the five idle links let in first give way, and it is answered
        status = await asyncio.wait_for(_ask(server.port), _status.PROMISE)
        assert isinstance(status, w.Status) and status.info["stats"]["status_evicted"] == 5
        assert [await r.read() for r, _ in idle[:5]] == [b""] * 5
        assert server.counters["status_refused_busy"] == 0
        for _, idle_writer in idle:
            idle_writer.close()
        await eventually(lambda: server.counters["status_answers"] == 2)
    finally:
        await server.close()


async def test_a_newcomer_waits_in_line_while_every_link_waits_for_its_answer(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(_status, "MAX_LINKS", 4)
    server = StatusServer("127.0.0.1:0", lambda: {"hello": 1})
    await server.start()
    try:
        assert isinstance(await _ask(server.port), w.Status)
        server._pacer.gap = 1.0  # the next Status is a second away: askers wait
        asking = [asyncio.create_task(_ask(server.port)) for _ in range(4)]
        await eventually(lambda: server.counters["status_paced"] == 4)
        assert server.counters["status_builds"] == 1  # they wait for the next: none built yet
        newcomer = asyncio.create_task(_ask(server.port))  # no slot: it waits its turn
        answers = await asyncio.gather(*asking, newcomer)
        assert all(isinstance(answer, w.Status) for answer in answers)
        counters = server.counters
        assert counters["status_evicted"] == counters["status_refused_busy"] == 0
        assert counters["status_builds"] == 3  # the four askers', then the newcomer's
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


async def test_an_address_it_cannot_serve_on_is_said_in_one_line() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        server = StatusServer(f"127.0.0.1:{port}", lambda: {})
        with pytest.raises(ConfigError) as error:
            await server.start()
    said = f"cannot serve the status on 127.0.0.1:{port}: Address already in use"
    assert str(error.value) == said
