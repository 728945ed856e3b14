"""``ups/_port.py``, the admission of the status and metrics ports, rule by rule, on real
sockets: first come first served, a turn for links that do not ask or do not read, none for
links the daemon holds up, bounded waits, and newcomers left in the kernel's queue while the
line is full.

The port here answers a line ``NAME SIZE`` with ``SIZE`` bytes (at least the name), and notes
the names in the order it answered them.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable

import pytest

from ups._port import _ANSWERING, _WRITING, BadRequest, Limits, Port, listen

from .conftest import eventually

_Stream = tuple[asyncio.StreamReader, asyncio.StreamWriter]


def _line_reader() -> Callable[[bytes], tuple[str, int] | None]:
    buf = bytearray()

    def feed(data: bytes) -> tuple[str, int] | None:
        buf.extend(data)
        if b"\n" not in buf:
            return None
        name, _, size = bytes(buf).partition(b"\n")[0].partition(b" ")
        if not size.isdigit():
            raise BadRequest(b"no\n")
        return name.decode(), int(size)

    return feed


class _Answers:
    """The port's answers: ``order`` of the names answered; ``hold`` keeps answers back."""

    def __init__(self) -> None:
        self.order: list[str] = []
        self.hold = asyncio.Event()
        self.hold.set()

    async def __call__(self, request: tuple[str, int]) -> bytes:
        name, size = request
        await self.hold.wait()
        self.order.append(name)
        return name.encode().ljust(size, b".")


@contextlib.asynccontextmanager
async def _port(**limits: float) -> AsyncIterator[tuple[Port[tuple[str, int]], _Answers]]:
    answers = _Answers()
    port = Port("the test port", _line_reader, answers, Limits(**limits))  # type: ignore[arg-type]
    await port.start(listen("127.0.0.1", 0))
    try:
        yield port, answers
    finally:
        await port.close()


def _state(port: Port[tuple[str, int]]) -> int | None:
    """The state of the link that holds the one slot (None: no link holds it)."""
    return next((link.state for link in port._links.values()), None)


async def _open(port: Port[tuple[str, int]]) -> _Stream:
    return await asyncio.open_connection("127.0.0.1", port.port)


async def _ask(stream: _Stream, name: str, size: int = 0) -> bytes:
    """Ask on ``stream``; what comes back until the port closes it."""
    reader, writer = stream
    writer.write(f"{name} {size}\n".encode())
    try:
        return await reader.read()
    finally:
        writer.close()


async def _closed(stream: _Stream) -> bool:
    """True once the port closed ``stream`` without a word."""
    reader, writer = stream
    try:
        return await asyncio.wait_for(reader.read(), 10) == b""
    except ConnectionError:
        return True
    finally:
        writer.close()


async def test_newcomers_are_let_in_first_come_first_served_as_idle_links_give_way() -> None:
    async with _port(links=1, waiting=8, turn=0.2, read_timeout=30) as (port, answers):
        idle = await _open(port)
        await eventually(lambda: len(port._links) == 1)
        asking = []
        for name in ("b", "c", "d"):  # each in line before the next connects
            asking.append(asyncio.create_task(_ask(await _open(port), name)))
            await eventually(lambda: len(port._line) == len(asking))
        assert [await a for a in asking] == [b"b", b"c", b"d"]
        assert answers.order == ["b", "c", "d"]  # in the order they came
        assert await _closed(idle)  # it held the one slot past its turn while others waited
        assert port.counters["evicted"] == 1 and port.counters["answers"] == 3


async def test_an_asker_answered_goes_to_the_back_of_the_line() -> None:
    async with _port(links=1, waiting=8, turn=5) as (port, answers):
        answers.hold.clear()  # the first asker holds the slot until its answer is let go
        first = asyncio.create_task(_ask(await _open(port), "a1"))
        await eventually(lambda: _state(port) == _ANSWERING)
        other = asyncio.create_task(_ask(await _open(port), "b"))
        await eventually(lambda: len(port._line) == 1)
        answers.hold.set()
        assert await first == b"a1"
        again = asyncio.create_task(_ask(await _open(port), "a2"))  # reconnects at once
        assert await other == b"b" and await again == b"a2"
        assert answers.order == ["a1", "b", "a2"]
        assert port.counters["evicted"] == 0  # never evicted while the daemon held it up


async def test_a_link_held_up_by_the_daemon_keeps_its_slot_and_a_newcomer_waits_bounded() -> None:
    async with _port(links=1, waiting=8, turn=0.05, wait_timeout=0.5) as (port, answers):
        answers.hold.clear()
        held = asyncio.create_task(_ask(await _open(port), "held"))
        await eventually(lambda: _state(port) == _ANSWERING)
        (link,) = port._links.values()
        loop = asyncio.get_running_loop()
        await eventually(lambda: loop.time() - link.since > 0.1)  # well past its turn
        late = await _open(port)
        assert await _closed(late)  # its wait in line has a bound: closed, counted
        assert port.counters["refused_busy"] == 1 and port.counters["evicted"] == 0
        answers.hold.set()
        assert await held == b"held"  # past its turn many times: the daemon held it, not it


async def test_a_link_that_does_not_read_its_answer_gives_way_after_its_turn() -> None:
    async with _port(links=1, waiting=8, turn=0.2, answer_timeout=60) as (port, _):
        _, writer = await _open(port)
        writer.write(b"big 67108864\n")  # 64 MiB that it never reads: the write waits
        await eventually(lambda: _state(port) == _WRITING)
        assert await _ask(await _open(port), "small") == b"small"
        assert port.counters["evicted"] == 1
        writer.close()


async def test_a_link_must_send_its_whole_request_in_time_trickling_or_not() -> None:
    async with _port(links=4, read_timeout=0.5) as (port, _):
        idle = await _open(port)
        trickling = await _open(port)
        _, writer = trickling
        loop = asyncio.get_running_loop()
        start = loop.time()
        closed = asyncio.create_task(_closed(trickling))
        while not closed.done():  # a byte every 0.1 s: each read is quick, the whole is not
            writer.write(b"x")
            await asyncio.wait({closed}, timeout=0.1)
        assert await closed and await _closed(idle)
        assert loop.time() - start < 5
        assert port.counters["timed_out"] == 2


async def test_what_is_not_a_request_is_answered_so_and_closed() -> None:
    async with _port() as (port, _):
        reader, writer = await _open(port)
        writer.write(b"what?\n")
        assert await reader.read() == b"no\n"
        writer.close()
        reader, writer = await _open(port)
        writer.write(b"x" * 2000)  # no request fits in more than max_request
        assert await reader.read() == b""
        writer.close()
        await eventually(lambda: port.counters["bad_requests"] == 2)


async def test_while_the_line_is_full_newcomers_wait_unaccepted_and_idle_links_go_first() -> None:
    async with _port(links=2, waiting=2, turn=1, read_timeout=30) as (port, _):
        idle = [await _open(port) for _ in range(4)]  # two served, two in line: full
        await eventually(lambda: len(port._links) == 2 and len(port._line) == 2)
        # the line is full: the newcomer waits in the kernel's queue; the link let in first,
        # which has not asked, gives way after a tenth of its turn (not a whole one), the
        # first in line takes its slot, and the newcomer gets a place in line
        newcomer = asyncio.create_task(_ask(await _open(port), "newcomer"))
        await eventually(lambda: port.counters["evicted"] >= 1, 0.9)
        assert await newcomer == b"newcomer"  # let in, at the latest, after the next turn
        assert port.counters["refused_busy"] == 0
        for stream in idle:
            stream[1].close()


@pytest.mark.parametrize("where", ["127.0.0.1", "::1"])
async def test_it_listens_where_it_is_told(where: str) -> None:
    try:
        sock = listen(where, 0)
    except OSError:
        pytest.skip(f"no {where} here")
    answers = _Answers()
    port = Port("the test port", _line_reader, answers, Limits())
    await port.start(sock)
    try:
        stream = await asyncio.open_connection(where, port.port)
        assert await _ask(stream, "here") == b"here"
    finally:
        await port.close()
