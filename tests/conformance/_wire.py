"""The test's own view of the bus: a raw python-can bus that sends frames built by ``_frames``
and records every frame it hears, and a node written from the document (``RawNode``)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any, NamedTuple

import can

from ups._canlink import CanLink
from ups.broker.c_ecb import CEcb
from ups.broker.can_ecb import CanEcb

from ._frames import (
    PUB_BIND,
    SUB_BIND,
    Assign,
    Bind,
    Census,
    Failed,
    Frame,
    Hello,
    Knock,
    Offer,
    PubAt,
    Query,
    Request,
    Stage,
    SubAt,
    TxNodesFull,
    claim,
    decode,
    message,
    nibbles,
)

Match = Frame | type | tuple[type, ...] | Callable[[Frame], bool]
#: the CAN-ECBs the suite runs against: ours in Python (broker/can_ecb.py) and in C
#: (libups-ecb, c/ups_ecb.h, through broker/c_ecb.py): compiled for this machine ("c") and its
#: Cortex-M0+ image in an emulator ("m0", the ecb-full image); the tests use only what all have
ECBS = ("python", "c", "m0")
Ecb = CanEcb | CEcb
REFUSAL_WAIT = 3.0  #: Timers: a refusal ends a join or request once it stood this long


class Heard(NamedTuple):
    at: float  #: loop time
    frame: Frame
    sent: bool  #: sent by this wire (True) or heard on the bus (False)


def _matches(match: Match, frame: Frame) -> bool:
    if isinstance(match, type):
        return isinstance(frame, match)
    if type(match) is tuple:  # a tuple of types (a frame is a NamedTuple, never a plain tuple)
        return isinstance(frame, match)
    if callable(match):
        return bool(match(frame))
    return frame == match


class Wire:
    """A raw python-can bus on the test's virtual channel, with a log of all it sent and heard.

    Frames are read by a task of the test's loop (polling ``recv(0)``), so the CAN-ECB and the
    nodes of the same loop keep running. ``handlers`` are called with every frame heard.
    """

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.log: list[Heard] = []
        self.handlers: list[Callable[[Frame], None]] = []
        self._loop = asyncio.get_running_loop()
        self._draining = False
        self._closed = False
        self._task = self._loop.create_task(self._pump())

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        self._drain()
        self._closed = True
        self.bus.shutdown()

    def _drain(self) -> bool:
        if self._draining or self._closed:
            return False
        self._draining = True
        got = False
        try:
            while (msg := self.bus.recv(0)) is not None:
                frame = decode(msg)
                self.log.append(Heard(self._loop.time(), frame, False))
                got = True
                for handler in list(self.handlers):
                    handler(frame)
        finally:
            self._draining = False
        return got

    async def _pump(self) -> None:
        while True:
            heard = self._drain()
            await asyncio.sleep(0 if heard else 0.0005)

    def send(self, *frames: Frame | can.Message) -> int:
        """Send ``frames`` back to back; returns the log index of the first one, so that
        ``since=`` that index means "after these frames were sent"."""
        self._drain()  # everything sent before ours is logged before ours
        start = len(self.log)
        for frame in frames:
            msg = frame if isinstance(frame, can.Message) else message(frame)
            self.bus.send(msg)
            logged = decode(msg) if isinstance(frame, can.Message) else frame
            self.log.append(Heard(self._loop.time(), logged, True))
        return start

    def mark(self) -> int:
        """The log index from which frames are heard after now."""
        self._drain()
        return len(self.log)

    def heard(self, since: int = 0, until: int | None = None) -> list[Frame]:
        """The frames heard (not sent) in ``log[since:until]``."""
        self._drain()
        return [h.frame for h in self.log[since:until] if not h.sent]

    def find(self, match: Match, since: int = 0, until: int | None = None) -> list[Frame]:
        return [f for f in self.heard(since, until) if _matches(match, f)]

    async def expect(
        self, match: Match, *, since: int = 0, timeout: float = 2.0
    ) -> tuple[int, Any]:
        """Wait for the first frame heard at or after ``since`` that matches; returns its log
        index and the frame. Fails after ``timeout`` seconds."""
        deadline = self._loop.time() + timeout
        i = since
        while True:
            self._drain()
            while i < len(self.log):
                entry = self.log[i]
                if not entry.sent and _matches(match, entry.frame):
                    return i, entry.frame
                i += 1
            if self._loop.time() > deadline:
                raise AssertionError(
                    f"expected {match!r} on the wire within {timeout} s; "
                    f"heard since: {self.heard(since)}"
                )
            await asyncio.sleep(0.001)

    async def expect_none(self, match: Match, *, since: int, window: float, what: str = "") -> None:
        """A negative check: no frame matching ``match`` is heard from ``since`` until
        ``window`` seconds from now (a bounded observation window, not a synchronisation)."""
        deadline = self._loop.time() + window
        while True:
            bad = self.find(match, since)
            assert not bad, f"{what + ': ' if what else ''}unexpected frames on the wire: {bad}"
            if self._loop.time() >= deadline:
                return
            await asyncio.sleep(0.002)


class RawNode:
    """A UPS node written from docs/protocol.md only, on a ``Wire``.

    It joins (Knock, Stage answers to Census and Query, knock retry; a TxNodesFull or Failed
    of its id ends the join once it has stood the refusal wait, 3 s, with no Offer or Assign of
    its id), asks for bindings, and answers Hello (CLAIM, SUB_AT, PUB_AT) at most once per
    second. A node that is already "joined" (for recovery tests) is made with ``txnode=``.
    """

    def __init__(self, wire: Wire, node_id: int, *, txnode: int | None = None) -> None:
        self.wire = wire
        self.node_id = node_id
        self.txnode = txnode
        self.subs: dict[int, int] = {}  #: uid -> etag it subscribes at
        self.pubs: dict[int, int] = {}  #: uid -> etag it publishes at
        self.failure: Frame | None = None  #: the latest refusal of its join
        self.refused_at: float | None = None  #: since when a refusal stands, uncontradicted
        self.answer_hello = True
        self.claim_offers = True
        self._loop = asyncio.get_running_loop()
        self._last_query = self._loop.time()
        self._last_answer = float("-inf")
        self._answer_due: asyncio.TimerHandle | None = None
        wire.handlers.append(self._on_frame)

    def close(self) -> None:
        if self._answer_due is not None:
            self._answer_due.cancel()
        with contextlib.suppress(ValueError):
            self.wire.handlers.remove(self._on_frame)

    # --- joining ----------------------------------------------------------------------------

    def _stages(self, epoch: int, start: int) -> None:
        ids = nibbles(self.node_id)
        self.wire.send(*(Stage(epoch, s, ids[s]) for s in range(start, 16)))

    def _on_frame(self, frame: Frame) -> None:
        if self.txnode is None:
            now = self._loop.time()
            if isinstance(frame, Census | Query | Hello) and self.refused_at is not None:
                self.refused_at = now  # "counted ... from the last Hello, Census or Query"
            match frame:
                case Census(epoch):
                    self._last_query = now
                    self._stages(epoch, 0)
                case Query(epoch, prefix):
                    self._last_query = now
                    if nibbles(self.node_id, len(prefix)) == prefix:
                        self._stages(epoch, len(prefix))
                case Offer(txnode, node_id) if node_id == self.node_id:
                    self._last_query = now
                    self.refused_at = None  # contradicted
                    if self.claim_offers:
                        self.wire.send(claim(txnode, self.node_id))
                case Assign(txnode, node_id) if node_id == self.node_id:
                    self.txnode = txnode
                case TxNodesFull(node_id) | Failed(node_id) if node_id == self.node_id:
                    self.failure = frame
                    if self.refused_at is None:
                        self.refused_at = now
            return
        match frame:
            case Hello() if self.answer_hello:
                self._hello()
            case Assign(txnode, node_id) if node_id == self.node_id and txnode != self.txnode:
                self.txnode = txnode
                self._announce()

    async def join(self, timeout: float = 15.0) -> int:
        """Knock until assigned; returns the TxNode. Knock retry: "50 ms, doubling to 1 s, and
        at least 0.3 s" after the last Knock, Census, Query or Offer heard. ``timeout``: 15 s,
        as the tests' Python nodes get (a census on a busy machine may wait up to 4 s)."""
        deadline = self._loop.time() + timeout
        retry = 0.05
        self.wire.send(Knock())
        knocked = self._loop.time()
        while self.txnode is None:
            now = self._loop.time()
            refused = self.refused_at is not None and now >= self.refused_at + REFUSAL_WAIT
            assert not refused, f"join of {self.node_id:#x} failed: {self.failure}"
            assert now < deadline, f"node {self.node_id:#x} not assigned within {timeout} s"
            quiet = now - max(knocked, self._last_query) >= max(retry, 0.3)
            if quiet and self.refused_at is None:  # "does not knock" while a refusal is open
                self.wire.send(Knock())
                knocked = now
                retry = min(2 * retry, 1.0)
            await asyncio.sleep(0.001)
        return self.txnode

    # --- binding ----------------------------------------------------------------------------

    def request(self, kind: int, value: int) -> Request:
        """A request frame of this node (it must hold a TxNode)."""
        assert self.txnode is not None
        return Request(kind, self.txnode, value)

    async def ask(self, kind: int, uid: int, *, timeout: float = 2.0) -> Bind:
        """Send one request (SUB_BIND or PUB_BIND) and wait for the Bind that answers it."""
        assert self.txnode is not None
        since = self.wire.send(Request(kind, self.txnode, uid))
        _, bind = await self.wire.expect(
            lambda f: isinstance(f, Bind) and f.uid == uid, since=since, timeout=timeout
        )
        assert isinstance(bind, Bind)
        if kind == SUB_BIND:
            self.subs[uid] = bind.etag
        elif kind == PUB_BIND:
            self.pubs[uid] = bind.etag
        return bind

    # --- the answer to Hello ------------------------------------------------------------------

    def _hello(self) -> None:
        if self._answer_due is not None:
            return
        wait = self._last_answer + 1.0 - self._loop.time()
        if wait <= 0:
            self._announce()
        else:
            self._answer_due = self._loop.call_later(wait, self._announce)

    def _announce(self) -> None:
        assert self.txnode is not None
        self._answer_due = None
        self._last_answer = self._loop.time()
        t = self.txnode
        frames: list[Frame] = [claim(t, self.node_id)]
        frames += [SubAt(t, etag, uid) for uid, etag in self.subs.items()]
        frames += [PubAt(t, etag, uid) for uid, etag in self.pubs.items()]
        self.wire.send(*frames)


async def txnode_of(wire: Wire, node_id: int, *, since: int = 0) -> int:
    """The TxNode the CAN-ECB assigned to ``node_id``, read from its Assign on the wire."""
    _, assign = await wire.expect(
        lambda f: isinstance(f, Assign) and f.node_id == node_id, since=since, timeout=5.0
    )
    return int(assign.txnode)


async def bound_etag(wire: Wire, request: Request, *, since: int = 0) -> int:
    """Wait for ``request`` on the wire, then for the Bind of its UID after it; its etag."""
    i, _ = await wire.expect(request, since=since)
    _, bind = await wire.expect(lambda f: isinstance(f, Bind) and f.uid == request.value, since=i)
    return int(bind.etag)


@contextlib.asynccontextmanager
async def serving_ecb(
    channel: str, state: Path, kind: str, *, recovery: float = 0.2
) -> AsyncIterator[Ecb]:
    """Our real CAN-ECB of ``kind`` (one of ``ECBS``) on its own link to the virtual
    ``channel``, its durable state in ``state`` (the SQLite file, or libups-ecb's blob)."""
    target = "m0" if kind == "m0" else "host"
    link = CanLink.open(f"virtual:{channel}")
    try:
        ecb: Ecb = (
            CanEcb(link, state, recovery=recovery)
            if kind == "python"
            else CEcb(link, state, recovery=recovery, target=target)
        )
    except BaseException:
        link.close()
        raise
    try:
        await ecb.start()
        yield ecb
    finally:
        ecb.close()
        link.close()
