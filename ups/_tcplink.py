"""One TCP connection carrying UPS frames, for nodes, the TCP-ECB and the gateway alike.

Receiving (asyncio calls the link's ``protocol``, a ``BufferedProtocol``): one buffer is reused for
every read; whole frames are decoded in place (``_tcpwire.parse``), events without building a frame
object. Bad bytes close this connection only. A frame larger than the buffer is read into a buffer
grown for it once its header has come: an anonymous memory mapping, which goes back to the system
whole when it is dropped (never kept in the allocator's pools); on a listening socket's links the
growth is taken from the socket's ``ReceiveBudget`` first, or the frame is refused before its body
is read (``ups/_tcpbounds.py``). Sending: the first frame after a read (on any link: an answer, a
forwarded event) is written at once, with nothing scheduled; the frames that follow it are queued
and written at the end of the loop iteration (or as soon as the queue is full), joined into writes
of about 64 KiB, so a burst costs a few system calls, not one each. A large event is queued as its
header and its data, and the data is handed to the transport as it is (never joined, never copied
here). Writing stops while the transport is paused (its buffer is full) and goes on when it
resumes. The event queue is bounded: while the peer does not read it fills up to ``limit`` frames
or ``limit_bytes`` bytes, then ``overflow`` decides which event is lost, and ``dropped`` counts it.
Control frames (everything but events: Hello, Start, registrations, ...) wait in a queue of their
own and are never dropped to make room; a peer that leaves ``CONTROL_LIMIT`` of them, or
``CONTROL_BYTES`` of them, unread is cut off.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import mmap
import struct
import time
from collections.abc import Callable
from typing import Any, cast

from . import _tcpwire as w
from ._errors import DecodeError
from ._face import Overflow
from ._tcpbounds import BASE_BUFFER, ReceiveBudget
from ._tcpbounds import Doorman as Doorman  # (re-exported: it lived here)
from ._tcpbounds import link_budget as link_budget

log = logging.getLogger("ups.tcp")

_BUFFER = BASE_BUFFER  # receive buffer to begin with; grown to hold a bigger frame whole ...
_BUFFER_KEEP = 1 << 18  # ... and given back once empty, when it grew past this (see trim)
HELD = 1  #: a reason to stop reading a link: its owner holds what it read (``pause_reading``)
_GROWING = 2  # ... the link waits to be admitted before it grows its buffer for a frame
_WRITE_HIGH = 1 << 16  # transport buffer above which it pauses us
QUEUE_BYTES = 64 << 20  #: events queued for a peer that does not read, in bytes (with ``limit``)
_BATCH = 1 << 16  # small frames joined into one write of about this many bytes
CONTROL_LIMIT = 1 << 14  #: control frames queued for a peer that does not read: then cut off
CONTROL_BYTES = 8 << 20  #: ... or this many bytes of them


class Link:
    """A connection: ``on_event(link, uid, data, priority, seq)`` and ``on_frame(link, frame)`` get
    what arrives, ``on_lost(link, reason)`` is called once when it ends (reason None: we closed
    it). ``peer`` is whatever the owner wants to remember about the other side. asyncio connects
    its ``protocol`` (the factory of ``create_connection``/``create_server`` returns that)."""

    def __init__(
        self,
        on_event: Callable[[Link, int, bytes, int, int], None],
        on_frame: Callable[[Link, w.Frame], None],
        on_lost: Callable[[Link, str | None], None],
        *,
        max_frame: int = w.DEFAULT_MAX_FRAME,
        limit: int = 1024,
        limit_bytes: int = QUEUE_BYTES,
        overflow: Overflow = "drop_oldest",
    ) -> None:
        self.peer: Any = None
        #: called once connected, before anything is written: a reason to abort, or None
        self.verify: Callable[[asyncio.BaseTransport], str | None] | None = None
        self.limit = limit
        self.overflow: Overflow = overflow
        self.dropped = 0
        self.transport: asyncio.Transport | None = None
        self._on_event = on_event
        self._on_frame = on_frame
        self._on_lost = on_lost
        self.max_frame = max_frame  #: the longest frame accepted (an owner may change it)
        #: the receive buffer: ``_BUFFER`` bytes of the heap, or a mapping grown for a frame
        self._buf: bytearray | mmap.mmap = bytearray(_BUFFER)
        self._start = 0
        self._end = 0
        #: where a grown buffer comes from (None: no bound but ``max_frame``; see Doorman)
        self.budget: ReceiveBudget | None = None
        self.may_grow = True  #: False while a Doorman has not admitted the link
        self._wants = 0  # the buffer a frame waits for, while it may not grow
        self._reading_paused = 0  # why reading is paused: HELD, _GROWING
        self.progress = 0  #: reads that completed a frame (a link that holds memory must)
        #: events: encoded frames, or (header, data) for a large one, its data written as it is
        self._out: collections.deque[bytes | tuple[bytes, bytes]] = collections.deque()
        self._out_bytes = 0  # what _out holds, in bytes
        self.limit_bytes = limit_bytes
        #: keep a grown receive buffer until ``trim`` (a link that big frames keep coming on)
        self.keep_big = False
        self._big_since_trim = False
        self._control: list[bytes] = []  # control frames, written before the events
        self._control_bytes = 0
        self._room: asyncio.Future[None] | None = None  # awaited by a publisher for room
        self._flush_pending = False
        self._epoch = -1  # _reads when this link last wrote a frame at once
        self._paused = False
        self._closing = False
        self._loop = asyncio.get_running_loop()
        #: ``time.time()`` of the latest read: the events' receive time (a float; Any so that
        #: the compiled build keeps one Python float per read, not one per event)
        self.read_at: Any = 0.0
        self.lost: asyncio.Future[str | None] = self._loop.create_future()
        self.full_frame = max_frame  # what max_frame becomes once a Doorman lets it in
        #: what asyncio calls: a BufferedProtocol that hands everything to this link
        self.protocol = _Protocol(self)

    def __repr__(self) -> str:
        return f"<Link {self.name} queued={len(self._out)} dropped={self.dropped}>"

    @property
    def name(self) -> str:
        if self.transport is None:
            return "(unconnected)"
        addr = self.transport.get_extra_info("peername")
        return f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)

    @property
    def queued(self) -> int:
        """Events waiting to be written."""
        return len(self._out)

    def send_control(self, frame: bytes) -> None:
        """Queue a frame that must not be lost (anything but an event), ahead of the events."""
        if self._closing:
            return
        if len(self._control) >= CONTROL_LIMIT or self._control_bytes > CONTROL_BYTES:
            self.abort(f"{len(self._control)} control frames ({self._control_bytes} bytes) "
                       "left unread")  # fmt: skip
            return
        self._control.append(frame)
        self._control_bytes += len(frame)
        if not self._flush_pending and self._writable():
            self._flush_pending = True
            self._loop.call_soon(self._flush)

    async def room(self) -> None:
        """Wait until the event queue has room (or the link is gone): backpressure."""
        while self.full and not self._closing and not self.lost.done():
            if self._room is None or self._room.done():
                self._room = self._loop.create_future()
            waiters: set[asyncio.Future[Any]] = {self._room, self.lost}
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)

    # --- sending ---------------------------------------------------------------------------

    def send(self, frame: bytes | tuple[bytes, bytes]) -> bool:
        """Queue one encoded event frame (or its header and its data); never blocks. False if
        it was dropped: the queue was full (and ``overflow`` is drop_newest), or the link is
        closing."""
        out = self._out
        if (
            self._flush_pending  # a batch is being gathered for the end of this iteration
            and not self._closing
            and len(out) < self.limit
            and self._out_bytes < self.limit_bytes
        ):  # the fast path of a burst, and of fan-out to many subscribers
            out.append(frame)
            self._out_bytes += len(frame) if type(frame) is bytes else _size(frame)
            return True
        if self._closing:
            self.dropped += 1
            return False
        if self.full:
            if self._writable():  # a producer that never yields: write the batch now
                self._flush()
            while out and self.full:  # the peer does not read fast enough
                self.dropped += 1
                if self.overflow == "drop_newest":
                    return False
                self._out_bytes -= _size(out.popleft())
        transport = self.transport
        if (
            not out
            and not self._control
            and self._epoch != _reads[0]
            and transport is not None
            and not self._paused
            and not self.lost.done()
        ):  # the first frame since something was read: no batch to join, out at once
            self._epoch = _reads[0]
            if type(frame) is bytes:
                transport.write(frame)
            else:
                _write(transport, frame)
            return True
        if not self._flush_pending and self._writable():
            self._flush_pending = True  # frames sent later in this loop iteration are batched
            self._loop.call_soon(self._flush)
        out.append(frame)
        self._out_bytes += _size(frame)
        return True

    @property
    def full(self) -> bool:
        """The event queue holds ``limit`` frames or ``limit_bytes`` bytes: ``room`` waits."""
        return len(self._out) >= self.limit or self._out_bytes >= self.limit_bytes

    def adopt(self, other: Link) -> None:
        """Queue what ``other`` (a lost link to the same peer) had not written yet."""
        frames = list(other._out)
        other._out.clear()
        other._out_bytes = 0
        excess = len(frames) - max(0, self.limit - len(self._out))
        if excess > 0:
            self.dropped += excess
            frames = frames[excess:] if self.overflow == "drop_oldest" else frames[:-excess]
        self._out.extend(frames)
        self._out_bytes += sum(_size(frame) for frame in frames)

    def _writable(self) -> bool:
        return self.transport is not None and not self._paused and not self.lost.done()

    def _flush(self) -> None:
        self._flush_pending = False
        out = self._out
        if (out or self._control) and self._writable():
            assert self.transport is not None
            if self._control:
                self.transport.write(b"".join(self._control))
                self._control.clear()
                self._control_bytes = 0
            self._write_out()
            if self._room is not None and not self._room.done() and not self.full:
                self._room.set_result(None)
        if self._closing and not out and not self._control and self.transport is not None:
            self.transport.close()  # writes what the transport holds, then closes

    def _write_out(self) -> None:
        """Write queued events until none is left or the transport pauses us (its buffer is
        full): what stays queued goes out when it resumes, so nothing is ever copied in bulk."""
        out, transport = self._out, self.transport
        assert transport is not None
        if out and self._out_bytes <= _BATCH and not self._paused:  # usual: all in one write
            try:
                data = b"".join(out)  # type: ignore[arg-type]
            except TypeError:  # a large event's (header, data) among them: one by one below
                pass
            else:
                out.clear()
                self._out_bytes = 0
                transport.write(data)
                return
        while out and not self._paused:
            if not isinstance(out[0], bytes):  # a large event: header, then data as it is
                frame = out.popleft()
                self._out_bytes -= _size(frame)
                _write(transport, frame)
                continue
            batch: list[bytes] = []
            size = 0
            while out and size < _BATCH and isinstance(out[0], bytes):
                small = out.popleft()
                batch.append(small)  # type: ignore[arg-type]
                size += len(small)
            self._out_bytes -= size
            transport.write(batch[0] if len(batch) == 1 else b"".join(batch))

    def pause_writing(self) -> None:
        self._paused = True

    def resume_writing(self) -> None:
        self._paused = False
        self._flush()

    def close(self) -> None:
        """Close once everything queued is written (``lost`` resolves then); an unconnected
        link closes at once, its queue unsent."""
        if self._closing:
            return
        self._closing = True
        if self.transport is None:
            if not self.lost.done():
                self._lost(None)
        else:
            self._flush()

    def abort(self, reason: str) -> None:
        """Drop the connection at once: bad bytes from the peer, or the peer went silent."""
        self._closing = True
        if self.transport is not None:
            self.transport.abort()
        if not self.lost.done():
            self._lost(reason)

    # --- receiving -------------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # uvloop's is no subclass
        if self._closing:  # refused before it was even connected (see Doorman)
            self.transport.abort()
            return
        if self.verify is not None and (why := self.verify(transport)) is not None:
            self.abort(why)
            return
        self.transport.set_write_buffer_limits(high=_WRITE_HIGH)
        self._flush()

    def get_buffer(self, sizehint: int) -> memoryview:
        buf = self._buf
        if self._end == len(buf) and self._start:  # full: the partial frame to the front
            rest = self._end - self._start
            with memoryview(buf) as view:  # (overlapping: moved, no copy made on the way)
                view[:rest] = view[self._start : self._end]
            self._start, self._end = 0, rest
        if self._end == len(buf):  # never so: a frame that does not fit was grown for, or
            # waits unread, or was refused. Whatever comes now is not read, and the link ends.
            if not self._closing:
                self.abort("receive buffer full")
            return memoryview(bytearray(_BUFFER))
        return memoryview(buf)[self._end :]

    def buffer_updated(self, nbytes: int) -> None:
        _reads[0] += 1
        if self._end == len(self._buf):  # read into the scratch of get_buffer: dropped
            return
        self._end += nbytes
        self.read_at = time.time()  # once per read, for every event in it
        first = self._start
        try:
            pos = first
            while True:  # frame by frame while a Doorman limits it: a Hello lifts the limit
                limited = self.max_frame != self.full_frame
                start = pos
                pos = w.parse(
                    self._buf,
                    pos,
                    self._end,
                    self.max_frame,
                    self,
                    self._on_event,
                    self._on_frame,
                    limited,
                )
                if not limited or pos in (start, self._end) or self._closing:
                    break
        except DecodeError as exc:
            log.warning("closed the link from %s: %s", self.name, exc)
            self.abort(f"bad frame: {exc}")
            return
        if pos != first:
            self.progress += 1
        if pos == self._end:
            if len(self._buf) > _BUFFER_KEEP:  # a big frame is through: give the memory back
                if not self.keep_big:
                    self._shrink()
                elif self._end > _BUFFER_KEEP:
                    self._big_since_trim = True
            self._start = self._end = 0
        else:
            self._start = pos
            if self._end - pos >= w.HEADER and not self._closing:  # (parse checked the header)
                (head,) = _HEAD.unpack_from(self._buf, pos)
                if w.HEADER + (head & w.MAX_BODY) > len(self._buf):
                    self._grow(w.HEADER + (head & w.MAX_BODY))

    def _grow(self, need: int) -> None:
        """Room for a frame of ``need`` bytes (header included), before its body is read: from
        the budget, if the link has one (else it is refused, and the link closed); not before
        the link is admitted (till then it is not read)."""
        if not self.may_grow:
            self._wants = need
            self.pause_reading(_GROWING)
            return
        self._wants = 0
        size = -(-need // mmap.PAGESIZE) * mmap.PAGESIZE
        if self.budget is not None and not self.budget.take(self, size - _BUFFER):
            self.abort(f"no room in the receive buffers for a frame of {need} bytes")
            return
        rest = self._end - self._start
        grown = mmap.mmap(-1, size)  # given back to the system as soon as it is dropped
        with memoryview(grown) as view, memoryview(self._buf) as old:
            view[:rest] = old[self._start : self._end]
        self._buf = grown
        self._start, self._end = 0, rest
        self.resume_reading(_GROWING)

    def admitted(self) -> None:
        """The link may grow its buffer (a Doorman admitted it): a frame that waited for that
        is read now."""
        self.may_grow = True
        if self._wants and not self._closing:
            self._grow(self._wants)

    def partial(self) -> bool:
        """Whether part of a frame waits in the receive buffer for the rest of it."""
        return self._start != self._end

    def shrink(self) -> None:
        """Give a grown receive buffer back, if it holds no partial frame (the budget's call)."""
        if len(self._buf) > _BUFFER and self._start == self._end and not self._closing:
            self._shrink()
            self._start = self._end = 0

    def _shrink(self) -> None:
        self._buf = bytearray(_BUFFER)
        if self.budget is not None:
            self.budget.release(self)

    def trim(self) -> None:
        """With ``keep_big``: give a grown receive buffer back if no big frame came since the
        last call (call it now and then, e.g. once a second)."""
        if not self._big_since_trim and len(self._buf) > _BUFFER_KEEP and self._start == self._end:
            self._shrink()
            self._start = self._end = 0
        self._big_since_trim = False

    def pause_reading(self, why: int) -> None:
        """Stop reading the link for ``why`` (HELD: its owner's reason), until every reason to
        is gone (``resume_reading``)."""
        if not self._reading_paused and self.transport is not None:
            self.transport.pause_reading()
        self._reading_paused |= why

    def resume_reading(self, why: int) -> None:
        was = self._reading_paused
        self._reading_paused &= ~why
        if was and not self._reading_paused and self.transport and not self.lost.done():
            self.transport.resume_reading()

    def eof_received(self) -> bool:
        return False  # close our side too

    def connection_lost(self, exc: Exception | None) -> None:
        self._buf = bytearray()  # nothing is read any more: a grown buffer goes back at once
        self._start = self._end = 0
        if self.budget is not None:
            self.budget.release(self)
        if not self.lost.done():
            reason = None if self._closing else (str(exc) if exc else "closed by peer")
            self._lost(reason)

    def _lost(self, reason: str | None) -> None:
        self.lost.set_result(reason)
        self._on_lost(self, reason)


class _Protocol(asyncio.BufferedProtocol):
    """A link as asyncio and uvloop see it. They want a ``BufferedProtocol`` subclass; the link
    itself is a plain class, which the compiled build (setup.py) makes a native one, so its
    per-event work never looks attributes up by name. Two calls more per read, none per event."""

    def __init__(self, link: Link) -> None:
        self._link = link

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._link.connection_made(transport)

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._link.get_buffer(sizehint)

    def buffer_updated(self, nbytes: int) -> None:
        self._link.buffer_updated(nbytes)

    def eof_received(self) -> bool:
        return self._link.eof_received()

    def connection_lost(self, exc: Exception | None) -> None:
        self._link.connection_lost(exc)

    def pause_writing(self) -> None:
        self._link.pause_writing()

    def resume_writing(self) -> None:
        self._link.resume_writing()


_HEAD = struct.Struct(">I")
#: reads on any link of this process: a frame sent after a read is written at once (an answer,
#: a forwarded event), further frames until the next read are batched at the end of the
#: loop iteration (a burst). Counted, not timed: the loop has no iteration number.
_reads = [0]


def _size(frame: bytes | tuple[bytes, bytes]) -> int:
    return len(frame) if isinstance(frame, bytes) else len(frame[0]) + len(frame[1])


def _write(transport: asyncio.Transport, frame: bytes | tuple[bytes, bytes]) -> None:
    if isinstance(frame, bytes):
        transport.write(frame)
    else:  # a large event: its header, then its data as it is
        transport.write(frame[0])
        transport.write(frame[1])
