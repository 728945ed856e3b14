"""A read-only port where whoever asks is answered, however many others hold links to it.

The CAN-ECB's ``--status`` port and every daemon's ``--metrics`` are such ports: a link sends
one request, gets one answer, and is closed. ``Port`` serves them with fair admission:

- at most ``Limits.links`` links are served at once; each must send its whole request within
  ``read_timeout`` of being let in, and have its answer made and written within
  ``answer_timeout`` (else closed: ``timed_out``);
- newcomers are let in in the order they came: when every slot is taken, up to ``waiting``
  of them wait in line, each ``wait_timeout`` at most (else closed: ``refused_busy``), and
  the next ones in the kernel's queue (``BACKLOG``), not taken until the line has room;
- while someone waits, a link that holds its slot past its *turn* gives way: of those that
  have not sent their whole request ``turn`` seconds after being let in, or have not taken
  their answer ``turn`` seconds after it was written, the one let in first is closed
  (``evicted``) and the first in line takes its slot; while the line is full, a link that
  has not asked gives way after ``GRACE`` of its turn already;
- a link that was answered is closed: to ask again, it goes to the back of the queue.

A link waiting for the daemon to make its answer (a Status build, a read of its counters) is
never evicted: the daemon, not the link, holds it up. So links that never ask, trickle, or do
not read hold a slot for a turn at most while others wait, and links that ask and reconnect
at once get one answer per place in the queue: a newcomer is answered after the links that
came before it, ``links`` of them at a time. What was counted is in ``counters``, and logged
at most once a second.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from collections.abc import Awaitable, Callable
from typing import Generic, NamedTuple, TypeVar

log = logging.getLogger("ups.port")

_R = TypeVar("_R")
_LOG_GAP = 1.0  # seconds between two logs of links turned away
_READING, _ANSWERING, _WRITING = range(3)
#: connections the kernel holds, in the order they came, while the line is full (on Linux, at
#: most net.core.somaxconn: 4096 by default)
BACKLOG = 4096
#: the share of its turn a link has, when the line is full, to send what it may have sent
#: before it was let in (it is read then: the loop's next steps)
GRACE = 0.1


def listen(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (its first address) for ``Port.start``; OSError
    when it cannot be had."""
    family, _, _, _, where = socket.getaddrinfo(
        host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
    )[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(where)
        sock.listen(BACKLOG)
    except BaseException:
        sock.close()
        raise
    return sock


class Limits(NamedTuple):
    links: int = 64  #: links served at once
    waiting: int = 64  #: links waiting in line for a slot, at most
    turn: float = 0.5  #: seconds a link may hold its slot idle (before asking, after its answer)
    read_timeout: float = 2.0  #: seconds a link has to send its whole request, once let in
    answer_timeout: float = 5.0  #: seconds its answer may take to be made and written
    wait_timeout: float = 5.0  #: seconds a link waits in line at most
    max_request: int = 1024  #: bytes a request may have


class BadRequest(Exception):
    """What a link sent is not a request: ``reply`` is written (if any), then it is closed."""

    def __init__(self, reply: bytes = b"") -> None:
        super().__init__("bad request")
        self.reply = reply


class _Link:
    __slots__ = ("evicted", "since", "state", "writer")

    def __init__(self, writer: asyncio.StreamWriter, now: float) -> None:
        self.writer = writer
        self.state = _READING
        self.since = now  # when it was let in, or its answer was written
        self.evicted = False


class Port(Generic[_R]):
    """Serves on a listening socket: each link's bytes go to a ``reader()`` of its own, fed
    what came so far, until it returns the request (or raises ``BadRequest``);
    ``answer(request)`` is written back, then the link is closed. ``name`` is for the log."""

    def __init__(
        self,
        name: str,
        reader: Callable[[], Callable[[bytes], _R | None]],
        answer: Callable[[_R], Awaitable[bytes]],
        limits: Limits,
    ) -> None:
        self.name = name
        self.limits = limits
        self._reader = reader
        self._answer = answer
        self.counters = dict.fromkeys(
            ("answers", "refused_busy", "evicted", "timed_out", "bad_requests"), 0
        )
        self.port = 0
        self._listener: socket.socket | None = None
        self._accepting: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[None]] = set()  # every link's, evicted ones too
        self._links: dict[asyncio.Task[None], _Link] = {}  # let in, in that order
        self._line: dict[asyncio.Task[None], tuple[asyncio.StreamWriter, asyncio.Future[None]]]
        self._line = {}  # waiting for a slot, first come first
        self._room = asyncio.Event()  # set when the line has room again
        self._timer: asyncio.TimerHandle | None = None
        self._closing = False
        self._logged_at = float("-inf")

    async def start(self, sock: socket.socket) -> None:
        """Serve on ``sock`` (``listen()``'s), which the port closes when it closes."""
        sock.setblocking(False)
        self._listener = sock
        self.port = sock.getsockname()[1]
        self._accepting = asyncio.create_task(self._accept(sock))

    async def close(self) -> None:
        self._closing = True
        if self._timer is not None:
            self._timer.cancel()
        if self._accepting is not None:
            self._accepting.cancel()
            await asyncio.gather(self._accepting, return_exceptions=True)
        if self._listener is not None:
            self._listener.close()
        tasks = list(self._tasks)
        for link in self._links.values():  # their reads end; cancelling them would log
            link.writer.transport.abort()
        for writer, admitted in self._line.values():
            writer.transport.abort()
            admitted.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    async def _accept(self, sock: socket.socket) -> None:
        """Take newcomers in the order they came, while the line has room; meanwhile they wait
        in the kernel's queue (``BACKLOG``), in the same order."""
        loop = asyncio.get_running_loop()
        while True:
            while len(self._line) >= self.limits.waiting:
                # overloaded: the oldest link that has not asked gives way now, turn or not,
                # to the first in line
                if self._evict(loop.time(), overloaded=True):
                    self._rotate()
                    continue
                self._room.clear()
                reading = [k.since for k in self._links.values() if k.state == _READING]
                grace = min(reading) + self.limits.turn * GRACE if reading else None
                with contextlib.suppress(TimeoutError):  # or until a grace ends
                    async with asyncio.timeout_at(grace):
                        await self._room.wait()
            conn, _ = await loop.sock_accept(sock)
            try:
                reader, writer = await asyncio.open_connection(
                    sock=conn, limit=self.limits.max_request
                )
            except OSError:  # gone already
                conn.close()
                continue
            task = loop.create_task(self._serve(reader, writer))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
            if len(self._links) < self.limits.links and not self._line:
                self._links[task] = _Link(writer, loop.time())
            else:
                self._line[task] = (writer, loop.create_future())
                self._rotate()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        try:
            if not await self._wait_turn(task):
                return
            link = self._links[task]
            request = await self._read(reader)
            if request is None or link.evicted:  # closed without asking
                return
            link.state = _ANSWERING
            async with asyncio.timeout(self.limits.answer_timeout):
                answer = await self._answer(request)
                link.state, link.since = _WRITING, asyncio.get_running_loop().time()
                if self._line:
                    self._schedule()  # its turn to take the answer begins
                writer.write(answer)
                await writer.drain()
            self.counters["answers"] += 1
        except TimeoutError:
            self._turned_away("timed_out")
        except BadRequest as bad:
            self.counters["bad_requests"] += 1
            with contextlib.suppress(Exception):
                writer.write(bad.reply)
        except ConnectionError:  # reset, or evicted: nothing to answer
            pass
        except asyncio.CancelledError:
            if not (self._closing and task.cancelling() == 0):
                raise  # else its answer was called off as the port closes: it ends quietly
        except Exception:  # a bug in answer(): logged there, the port serves on
            self.counters["bad_requests"] += 1
        finally:
            self._leave(task)
            writer.close()

    async def _wait_turn(self, task: asyncio.Task[None]) -> bool:
        """Wait in line, if ``task``'s link is in it, for a slot; False: it is closed."""
        entry = self._line.get(task)
        if entry is None:
            return task in self._links
        try:
            await asyncio.wait({entry[1]}, timeout=self.limits.wait_timeout)
        finally:
            if self._line.pop(task, None) is not None:
                self._room.set()
            entry[1].cancel()
        if task in self._links:
            return True
        if not self._closing:
            self._turned_away("refused_busy")
        return False

    async def _read(self, reader: asyncio.StreamReader) -> _R | None:
        """The link's request, once whole within ``read_timeout``; None if it closed first."""
        feed = self._reader()
        size = 0
        async with asyncio.timeout(self.limits.read_timeout):
            while data := await reader.read(self.limits.max_request):
                size += len(data)
                request = feed(data)
                if request is not None:
                    return request
                if size >= self.limits.max_request:
                    raise BadRequest()
        return None

    def _leave(self, task: asyncio.Task[None]) -> None:
        if self._links.pop(task, None) is not None and self._line and not self._closing:
            self._rotate()

    def _rotate(self) -> None:
        """Let in whoever waits first, into a free slot or one whose holder's turn is over."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        now = asyncio.get_running_loop().time()
        while self._line:
            if len(self._links) >= self.limits.links and not self._evict(now):
                break
            task, (writer, admitted) = next(iter(self._line.items()))
            del self._line[task]
            self._room.set()
            if not admitted.done():  # else it stopped waiting meanwhile
                self._links[task] = _Link(writer, now)
                admitted.set_result(None)
        if self._line:
            self._schedule()

    def _evict(self, now: float, overloaded: bool = False) -> bool:
        """Close the link that has held its slot longest past its turn (``overloaded``: or has
        not asked ``GRACE`` of a turn after it was let in); False if none has."""
        turn = self.limits.turn
        over = [
            (link.since, task)
            for task, link in self._links.items()
            if link.state != _ANSWERING
            and (
                now - link.since >= turn
                or (overloaded and link.state == _READING and now - link.since >= turn * GRACE)
            )
        ]
        if not over:
            return False
        _, task = min(over, key=lambda found: found[0])
        link = self._links.pop(task)
        link.evicted = True
        link.writer.transport.abort()  # its read or its write ends: its task returns
        self._turned_away("evicted")
        return True

    def _schedule(self) -> None:
        """Rotate again when the next turn ends (someone waits)."""
        ends = [link.since for link in self._links.values() if link.state != _ANSWERING]
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if ends:
            loop = asyncio.get_running_loop()
            self._timer = loop.call_at(min(ends) + self.limits.turn, self._rotate)

    def _turned_away(self, counter: str) -> None:
        """Count a link closed by a bound; log the counts at most once a second."""
        self.counters[counter] += 1
        now = time.monotonic()
        if now - self._logged_at >= _LOG_GAP:
            self._logged_at = now
            c, limits = self.counters, self.limits
            log.warning(
                "%s: closed %d links that held a slot past their %g s turn while others waited "
                "(%d links at once), %d that did not ask within %g s or were not answered "
                "within %g s, %d that found no slot within %g s (%d waiting at most)",
                self.name, c["evicted"], limits.turn, limits.links, c["timed_out"],
                limits.read_timeout, limits.answer_timeout, c["refused_busy"],
                limits.wait_timeout, limits.waiting,
            )  # fmt: skip
