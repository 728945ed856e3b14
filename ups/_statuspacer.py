"""Status answers that cost a bounded share of the event loop, however many ask.

``StatusPacer`` answers the StatusRequests of every link of a daemon (a node's listening port,
the TCP-ECB, the CAN-ECB's status port): a Status is built at most once per ``STATUS_GAP``
seconds, whoever asks and however often (docs/protocol.md, *Bounds on every listening socket*).
``StatusGate`` stands before a node's pacer with TLS: it answers only the identities the TCP-ECB
names (the ACL's ``status`` right; docs/protocol.md, *Access control*).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from . import _tcpwire as w
from ._tls import identity

if TYPE_CHECKING:
    from ._tcplink import Link

log = logging.getLogger("ups.tcp")

STATUS_GAP = 0.5  #: seconds: a daemon builds its Status at most this often, however many ask
_LOG_GAP = 1.0  # seconds between two logs of the same bound


class StatusPacer:
    """Answers StatusRequests with ``build()``, built at most once per ``gap`` seconds.

    A request is answered with a Status built after it came: at the end of the loop iteration
    if the last build is ``gap`` old (every request of that iteration shares the build), else
    with the next build, ``gap`` after the end of the last one. So however many links ask, and
    however often, the daemon spends at most one build per ``gap`` on them, and the rest of
    the time on its own work (keep-alives, registrations). A link's requests that wait together
    get one answer. Requests that had to wait are counted (``status_paced`` in ``counters``,
    beside ``status_builds`` and ``status_answers``) and logged at most once a second.
    """

    def __init__(
        self,
        build: Callable[[], dict[str, Any]],
        counters: dict[str, int],
        *,
        who: str,
        gap: float = STATUS_GAP,
    ) -> None:
        self._build = build
        self._counters = counters
        for key in ("status_builds", "status_answers", "status_paced"):
            counters.setdefault(key, 0)
        self._who = who
        self.gap = gap
        self._built_at = -math.inf  # loop time at the end of the last build
        self._links: dict[Link, None] = {}  # waiting for the next build, in order
        self._next: asyncio.Future[bytes] | None = None  # the next build, for next_frame
        self._timer: asyncio.Handle | None = None  # the next build, scheduled
        self._logged_at = -math.inf

    def ask(self, link: Link) -> None:
        """``link`` sent a StatusRequest: it gets the next Status."""
        if link in self._links:
            self._paced()
            return
        self._links[link] = None
        self._schedule()

    async def next_frame(self) -> bytes:
        """The next Status frame, encoded (for a server that writes it itself)."""
        if self._next is None:
            self._next = asyncio.get_running_loop().create_future()
        fut = self._next
        self._schedule()
        return await asyncio.shield(fut)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._links.clear()
        if self._next is not None:
            self._next.cancel()
            self._next = None

    def _schedule(self) -> None:
        loop = asyncio.get_running_loop()
        wait = self._built_at + self.gap - loop.time()
        if wait > 0:
            self._paced()
        if self._timer is None:
            self._timer = (
                loop.call_later(wait, self._answer) if wait > 0 else loop.call_soon(self._answer)
            )

    def _paced(self) -> None:
        self._counters["status_paced"] += 1
        now = time.monotonic()
        if now - self._logged_at >= _LOG_GAP:
            self._logged_at = now
            log.info(
                "%s builds its Status at most every %g s: status requests wait for the next "
                "(%d so far)", self._who, self.gap, self._counters["status_paced"],
            )  # fmt: skip

    def _answer(self) -> None:
        self._timer = None
        links, self._links = self._links, {}
        fut, self._next = self._next, None
        frame: bytes | None = None
        try:
            frame = w.encode(w.Status(self._build()))
        except Exception as exc:  # a bug in build(): logged, the askers are let go
            log.exception("%s could not build its Status", self._who)
            if fut is not None and not fut.done():
                fut.set_exception(exc)
                fut.exception()  # retrieved: every waiter may have gone meanwhile
        # the gap is time the loop has for other work: it starts after the build
        self._built_at = asyncio.get_running_loop().time()
        self._counters["status_builds"] += 1
        for link in links:
            if frame is None:
                link.abort("could not build the status")
            elif not link.lost.done():
                link.send_control(frame)
                self._counters["status_answers"] += 1
        if frame is not None and fut is not None and not fut.done():
            fut.set_result(frame)


class StatusGate:
    """Who may read a node's Status on its own links (its listening port, its links to
    subscribers): with TLS, the identities the TCP-ECB named last (``told``, from its
    ``StatusReaders``; None there: every identity of the fleet), and no one before it named
    any; without TLS, everyone (plain TCP names no one). Others get Refused(0, "status"),
    counted (``status_denied``) and logged at most once a second."""

    def __init__(
        self, answer: Callable[[Link], None], counters: dict[str, int], *, checking: bool
    ) -> None:
        self._answer = answer  # the pacer's ask: answers with the next Status
        self._counters = counters
        counters.setdefault("status_denied", 0)
        self._checking = checking
        self.readers: frozenset[str] | None = frozenset()  # None: every identity
        self._logged_at = -math.inf

    def told(self, readers: tuple[str, ...] | None) -> None:
        """The TCP-ECB names the identities that may read Status (None: all of the fleet)."""
        self.readers = None if readers is None else frozenset(readers)

    def ask(self, link: Link) -> None:
        """``link`` sent a StatusRequest: the next Status, if its identity may read it."""
        if self._checking and self.readers is not None:
            who = identity(link.transport)
            if who not in self.readers:
                self._counters["status_denied"] += 1
                now = time.monotonic()
                if now - self._logged_at >= _LOG_GAP:
                    self._logged_at = now
                    log.warning("refused its status to %s (%s): the TCP-ECB does not name it "
                                "among those that may read it (%d refused so far)", who,
                                link.name, self._counters["status_denied"])  # fmt: skip
                reason = f"identity {who!r:.80} may not read this node's status"
                link.send_control(w.encode(w.Refused(0, "status", reason)))
                return
        self._answer(link)
