"""Bounds on what the links of one listening socket may take: connections and receive memory.

``Doorman`` bounds the connections a listening socket accepts (how many, how long they may wait
to be admitted, how large their frames may be until then). ``ReceiveBudget`` bounds the memory
their receive buffers hold together: each link reads into a base buffer of its own
(``BASE_BUFFER``); a frame larger than that is read into a buffer grown for it, and that growth
is taken from the budget (``RECEIVE_BUDGET`` by default), only for links that were admitted.
docs/protocol.md (*Bounds on every listening socket*, *Receive buffers*) says it for people.

Both see a link only as ``Bounded``: the few things they read and call on it (``_tcplink.Link``
is one), so that this module stands below the links it bounds.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import resource
import time
from typing import Protocol

log = logging.getLogger("ups.tcp")

BASE_BUFFER = 1 << 14  #: each link's own receive buffer: all a link not admitted may fill
RECEIVE_BUDGET = 64 << 20  #: bytes the links of one listening socket may grow their buffers by
FRAME_TIME = 10.0  #: seconds: a link holding a grown buffer must complete a frame within this
_SWEEP = 1.0  # seconds between two looks for links that hold a grown buffer and make no progress
_LOG_GAP = 1.0  # seconds between two logs of the same bound


class Bounded(Protocol):
    """A link as the bounds see it (``_tcplink.Link``)."""

    budget: ReceiveBudget | None  #: where it grows its receive buffer from (a Doorman sets it)
    may_grow: bool  #: False until a Doorman admits it
    max_frame: int  #: the longest frame it accepts now
    full_frame: int  #: what ``max_frame`` becomes once a Doorman lets it in
    progress: int  #: reads that completed a frame
    lost: asyncio.Future[str | None]  #: done once it ended

    @property
    def name(self) -> str: ...
    def partial(self) -> bool:
        """Whether part of a frame waits in its receive buffer for the rest of it."""

    def shrink(self) -> None:
        """Give a grown receive buffer back, if it holds no partial frame."""

    def admitted(self) -> None:
        """A Doorman admitted it: it may grow its buffer from now on."""

    def abort(self, reason: str) -> None: ...


class ReceiveBudget:
    """The memory by which a daemon's links may grow their receive buffers, in all.

    A link asks (``take``) for the size its grown buffer will have beyond its base before it
    reads the body of a frame that does not fit its base buffer. When the budget cannot give it
    (after taking back the grown buffers that hold no partial frame: ``Bounded.shrink``), the
    frame is refused and the link closed (``receive_refused``). A link holding a grown buffer
    with a partial frame in it must complete a frame at least every ``frame_time`` seconds, or
    it is closed (``receive_stalled``): nobody holds the budget by sending slowly. ``counters``
    gets those counts and ``receive_held``, the bytes given out now.
    """

    def __init__(
        self,
        total: int,
        counters: dict[str, int],
        *,
        frame_time: float = FRAME_TIME,
    ) -> None:
        self.total = total
        self.frame_time = frame_time
        self.counters = counters
        for key in ("receive_refused", "receive_stalled", "receive_held"):
            counters.setdefault(key, 0)
        self.held = 0  #: bytes given out now
        self._holders: dict[Bounded, int] = {}  # link -> bytes it holds beyond its base
        self._seen: dict[Bounded, tuple[int, float]] = {}  # link -> (its progress, since when)
        self._timer: asyncio.TimerHandle | None = None
        self._logged_at = -math.inf

    def take(self, link: Bounded, size: int) -> bool:
        """``link`` grows its buffer to ``size`` bytes beyond its base: whether it may."""
        more = size - self._holders.get(link, 0)
        if self.held + more > self.total:
            self._reclaim(link)
            if self.held + more > self.total:
                self.counters["receive_refused"] += 1
                self._log(
                    "refused a frame from %s: it needs %d bytes of receive buffer more, and the "
                    "links of its socket hold %d of their %d (%d frames refused so far)",
                    link.name, more, self.held, self.total, self.counters["receive_refused"],
                )  # fmt: skip
                return False
        self._set(self.held + more)
        self._holders[link] = size
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(_SWEEP, self._sweep)
        return True

    def release(self, link: Bounded) -> None:
        """``link`` is back to its base buffer (or gone): what it held is free again."""
        size = self._holders.pop(link, 0)
        self._seen.pop(link, None)
        if size:
            self._set(self.held - size)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _set(self, held: int) -> None:
        self.held = held
        self.counters["receive_held"] = held

    def _reclaim(self, keep: Bounded) -> None:
        """Take back every grown buffer that holds no partial frame (a publisher's link keeps
        one between large events), but ``keep``'s."""
        for link in list(self._holders):
            if link is not keep:
                link.shrink()

    def _sweep(self) -> None:
        """Close the links that hold a grown buffer with a partial frame in it and completed
        no frame for ``frame_time`` seconds."""
        self._timer = None
        now = time.monotonic()
        for link in list(self._holders):
            if not link.partial() or link.lost.done():
                self._seen.pop(link, None)
                continue
            seen = self._seen.get(link)
            if seen is None or seen[0] != link.progress:
                self._seen[link] = (link.progress, now)
            elif now - seen[1] >= self.frame_time:
                self._seen.pop(link)
                self.counters["receive_stalled"] += 1
                self._log(
                    "closed the link from %s: it holds %d bytes of receive buffer and completed "
                    "no frame in %g s (%d links so closed)", link.name, self._holders[link],
                    self.frame_time, self.counters["receive_stalled"],
                )  # fmt: skip
                link.abort(f"no frame completed in {self.frame_time:g} s")
        if self._holders:
            self._timer = asyncio.get_running_loop().call_later(_SWEEP, self._sweep)

    def _log(self, message: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._logged_at >= _LOG_GAP:
            self._logged_at = now
            log.warning(message, *args)


class Doorman:
    """Bounds the connections one listening socket accepts, and counts what it turns away.

    At most ``max_links`` connections in all. A new one beyond closes the oldest connection
    still waiting to be admitted (``evicted``), or, if none waits, is closed itself
    (``refused``). At most ``max_waiting`` may wait to be admitted: when another comes, the
    oldest waiting one is closed (``evicted``); one that ``asked`` a question the daemon
    answers (a StatusRequest) goes after every waiting one that did not. A connection not
    admitted (``greeted``) within ``hello_timeout`` seconds is closed (``timed_out``). Until
    ``lift`` or ``greeted``, a connection may send frames of at most ``first_frame`` bytes.
    Until ``greeted`` it may not grow its receive buffer; once admitted it grows it from
    ``budget`` (``receive_budget`` bytes for all the socket's links, counted in ``counters``
    unless others are given).
    """

    def __init__(
        self,
        max_links: int,
        *,
        max_waiting: int = 256,
        hello_timeout: float = 5.0,
        first_frame: int = 4096,
        receive_budget: int = RECEIVE_BUDGET,
        counters: dict[str, int] | None = None,
    ) -> None:
        self.max_links = max_links
        self.max_waiting = max_waiting
        self.hello_timeout = hello_timeout
        self.first_frame = first_frame
        self.links = 0
        self._waiting: dict[Bounded, asyncio.TimerHandle] = {}  # oldest first
        self._asked: set[Bounded] = set()  # waiting, and owed an answer: evicted last
        self.counters = dict.fromkeys(("refused", "evicted", "timed_out"), 0)
        self.budget = ReceiveBudget(receive_budget, self.counters if counters is None else counters)

    def admit(self, link: Bounded) -> None:
        """A new connection (call from the protocol factory)."""
        self.links += 1
        link.budget = self.budget
        link.may_grow = False
        if self.links > self.max_links:
            if not self._waiting:
                self.counters["refused"] += 1
                link.abort(f"more than {self.max_links} connections")
                return
            self.counters["evicted"] += 1  # one not admitted yet makes room for the new one
            self._evictee().abort(f"more than {self.max_links} connections, and not admitted")
        if len(self._waiting) >= self.max_waiting:
            self.counters["evicted"] += 1
            self._evictee().abort(f"more than {self.max_waiting} connections without Hello")
        link.max_frame, link.full_frame = self.first_frame, link.max_frame
        loop = asyncio.get_running_loop()
        self._waiting[link] = loop.call_later(self.hello_timeout, self._time_out, link)

    def asked(self, link: Bounded) -> None:
        """``link`` asked what the daemon answers (a StatusRequest): while it waits to be
        admitted, it is evicted only after every waiting link that did not ask."""
        if link in self._waiting:
            self._asked.add(link)

    def _evictee(self) -> Bounded:
        """The oldest waiting link that asked nothing, else the oldest waiting one."""
        for link in self._waiting:
            if link not in self._asked:
                return link
        return next(iter(self._waiting))

    def greeted(self, link: Bounded) -> None:
        """``link`` said Hello (and is admitted): it may stay, send full-sized frames, and grow
        its receive buffer to read them."""
        self.lift(link)
        self._asked.discard(link)
        timer = self._waiting.pop(link, None)
        if timer is not None:
            timer.cancel()
        link.admitted()

    def lift(self, link: Bounded) -> None:
        """``link`` may send full-sized frames, but still counts as waiting to be admitted
        (``greeted``): it is still timed out, and evicted first; a frame larger than its base
        buffer waits, unread, until it is admitted."""
        link.max_frame = link.full_frame

    def gone(self, link: Bounded) -> None:
        """``link`` ended (call from its on_lost)."""
        self.links -= 1
        self._asked.discard(link)
        timer = self._waiting.pop(link, None)
        if timer is not None:
            timer.cancel()

    def _time_out(self, link: Bounded) -> None:
        if link in self._waiting:
            self.counters["timed_out"] += 1
            link.abort(f"not admitted (no Hello, or none vouched for) within "
                       f"{self.hello_timeout:g} s")  # fmt: skip

    def close(self) -> None:
        for timer in self._waiting.values():
            timer.cancel()
        self._waiting.clear()
        self.budget.close()


def link_budget(ceiling: int = 4096, reserve: int = 64) -> int:
    """How many connections a daemon may hold: ``ceiling``, or fewer if the process's limit on
    open files (raised to its hard limit first) leaves less, ``reserve`` kept for the rest."""
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft != hard:
            with contextlib.suppress(ValueError, OSError):
                resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
                soft = hard
    except (ValueError, OSError):
        return ceiling
    if soft == resource.RLIM_INFINITY:
        return ceiling
    return max(16, min(ceiling, soft - reserve))
