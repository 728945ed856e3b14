"""The event subscriptions of JAUS's Events service (core 1.1, ``Events.xml``): a client asks,
with Create Event, for the answer to one of its queries either periodically or on every change,
and gets Event messages carrying that answer until it cancels, or until it has been silent for
``EVENT_TIMEOUT`` seconds.

This module keeps the table and the timers; the host says what a query is answered with
(``answer``), what report a query yields (``report_of``) and how an Event reaches its client
(``send``). Bounds, each counted where it bites:

- ``MAX_EVENTS`` subscriptions at once, all clients together (``events_refused``);
- the rate: periodic and every-change events alike are sent at most ``cap(report)`` times a
  second (the mapping's ``rate``, else ``MAX_RATE``); a faster request is confirmed at the cap,
  changes arriving faster are coalesced into one Event with the latest answer
  (``events_coalesced``), never queued;
- a periodic tick with nothing to answer yet is skipped (``not_yet``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger("ups.jaus")

MAX_EVENTS = 64  #: event subscriptions held at once, all clients together
MAX_RATE = 25.0  #: events per second at most, for a report the mapping gives no rate
EVENT_TIMEOUT = 60.0  #: seconds a client may stay silent before its events are cancelled
PERIODIC, EVERY_CHANGE = 0, 1  #: Create Event's event types


@dataclass
class Subscription:
    event_id: int
    request_id: int
    owner: Hashable  #: the client, as the host names it (its id)
    route: Any  #: how the host reaches it
    kind: int
    rate: float  #: the confirmed rate (periodic) or the cap (every change)
    query: bytes  #: the query message: code (u16 LE) and payload
    report: str
    sequence: int = 0
    last_sent: float = -1e9
    heard: float = field(default_factory=time.monotonic)
    timer: asyncio.Handle | None = None


class EventRefused(Exception):
    """Create or Update Event cannot be honoured; ``code`` is Reject Event Request's
    response code."""

    def __init__(self, code: int, why: str) -> None:
        super().__init__(why)
        self.code = code


# Reject Event Request's response codes
PERIODIC_UNSUPPORTED, CHANGE_UNSUPPORTED, CONNECTION_REFUSED = 1, 2, 3
INVALID_SETUP, MESSAGE_UNSUPPORTED, INVALID_EVENT_ID = 4, 5, 6


class Events:
    def __init__(
        self,
        *,
        report_of: Callable[[bytes], str | None],
        answer: Callable[[bytes], Any | None],
        send: Callable[[Subscription, Any], None],
        cap: Callable[[str], float],
        counters: dict[str, int],
        max_events: int = MAX_EVENTS,
        timeout: float = EVENT_TIMEOUT,
    ) -> None:
        self._report_of, self._answer, self._send, self._cap = report_of, answer, send, cap
        self.counters = counters
        for name in (
            "events_created",
            "events_refused",
            "events_cancelled",
            "events_expired",
            "events_sent",
            "events_coalesced",
            "event_errors",
            "not_yet",
        ):
            counters.setdefault(name, 0)
        self.max_events = max_events
        self.timeout = timeout
        self.table: dict[int, Subscription] = {}

    def create(
        self, owner: Hashable, route: Any, request_id: int, kind: int, rate: float, query: bytes
    ) -> Subscription:
        """A new subscription, its first Event sent just after (once there is an answer);
        :class:`EventRefused` otherwise."""
        report = self._check(kind, rate, query)
        if len(self.table) >= self.max_events:
            self.counters["events_refused"] += 1
            raise EventRefused(CONNECTION_REFUSED, f"{self.max_events} events held already")
        event_id = next(i for i in range(256) if i not in self.table)
        sub = Subscription(event_id, request_id, owner, route, kind, 0.0, query, report)
        self._setup(sub, kind, rate)
        self.table[event_id] = sub
        self.counters["events_created"] += 1
        self._first(sub)
        return sub

    def update(
        self,
        owner: Hashable,
        route: Any,
        request_id: int,
        kind: int,
        rate: float,
        event_id: int,
        query: bytes,
    ) -> Subscription:
        sub = self.table.get(event_id)
        if sub is None or sub.owner != owner:
            raise EventRefused(INVALID_EVENT_ID, f"no event {event_id} of this client")
        report = self._check(kind, rate, query)
        self._stop(sub)
        sub.request_id, sub.route, sub.query, sub.report = request_id, route, query, report
        self._setup(sub, kind, rate)
        self._first(sub)
        return sub

    def cancel(self, owner: Hashable, event_id: int) -> Subscription:
        sub = self.table.get(event_id)
        if sub is None or sub.owner != owner:
            raise EventRefused(INVALID_EVENT_ID, f"no event {event_id} of this client")
        self._remove(sub)
        self.counters["events_cancelled"] += 1
        return sub

    def heard_from(self, owner: Hashable, now: float) -> None:
        for sub in self.table.values():
            if sub.owner == owner:
                sub.heard = now

    def expire(self, now: float) -> list[Subscription]:
        """Cancel the events of clients silent for ``timeout`` seconds; they are returned."""
        gone = [sub for sub in self.table.values() if now - sub.heard > self.timeout]
        for sub in gone:
            self._remove(sub)
            self.counters["events_expired"] += 1
        return gone

    def drop_owner(self, owner: Hashable) -> int:
        subs = [sub for sub in self.table.values() if sub.owner == owner]
        for sub in subs:
            self._remove(sub)
        return len(subs)

    def changed(self, report: str) -> None:
        """A new event arrived on the channel behind ``report``."""
        for sub in list(self.table.values()):
            if sub.kind == EVERY_CHANGE and sub.report == report:
                self._fire(sub)

    def close(self) -> None:
        for sub in list(self.table.values()):
            self._remove(sub)

    # --- internals -------------------------------------------------------------------------

    def _check(self, kind: int, rate: float, query: bytes) -> str:
        if kind not in (PERIODIC, EVERY_CHANGE):
            raise EventRefused(
                INVALID_SETUP, f"event type {kind} is neither periodic (0) nor every change (1)"
            )
        report = self._report_of(query)
        if report is None:
            raise EventRefused(MESSAGE_UNSUPPORTED, "no report answers that query here")
        if kind == PERIODIC and not rate > 0:
            raise EventRefused(INVALID_SETUP, "a periodic event needs a rate above 0")
        return report

    def _setup(self, sub: Subscription, kind: int, rate: float) -> None:
        cap = self._cap(sub.report)
        sub.kind = kind
        sub.rate = min(rate, cap) if kind == PERIODIC else cap

    def _first(self, sub: Subscription) -> None:
        """The first Event goes out right after the confirmation the caller sends now."""
        sub.timer = asyncio.get_running_loop().call_soon(self._due, sub)

    def _fire(self, sub: Subscription) -> None:
        """Send the answer now, unless the rate forbids it; then what comes next is timed."""
        loop = asyncio.get_running_loop()
        now = loop.time()
        interval = 1.0 / sub.rate
        if sub.kind == EVERY_CHANGE and sub.timer is not None:
            if now - sub.last_sent < interval:
                self.counters["events_coalesced"] += 1  # a send is due: it takes the latest
                return
            sub.timer.cancel()  # due by now: send at once, not at the timer's (late) tick,
            sub.timer = None  # the change that set the timer going with this one
            self.counters["events_coalesced"] += 1
        if sub.kind == EVERY_CHANGE and now - sub.last_sent < interval:
            sub.timer = loop.call_at(sub.last_sent + interval, self._due, sub)
            return
        self._send_answer(sub, now)
        if sub.kind == PERIODIC:
            sub.timer = loop.call_at(now + interval, self._due, sub)

    def _due(self, sub: Subscription) -> None:
        sub.timer = None
        if self.table.get(sub.event_id) is not sub:
            return
        try:
            self._fire(sub)
        except Exception:  # a broken answer cancels this event, never the others
            self.counters["event_errors"] += 1
            log.exception("event %d of %s failed: cancelled", sub.event_id, sub.owner)
            self._remove(sub)

    def _send_answer(self, sub: Subscription, now: float) -> None:
        report = self._answer(sub.query)
        if report is None:
            self.counters["not_yet"] += 1
            return
        sub.last_sent = now
        self._send(sub, report)
        sub.sequence = (sub.sequence + 1) & 0xFF
        self.counters["events_sent"] += 1

    def _stop(self, sub: Subscription) -> None:
        if sub.timer is not None:
            sub.timer.cancel()
            sub.timer = None

    def _remove(self, sub: Subscription) -> None:
        self._stop(sub)
        self.table.pop(sub.event_id, None)


__all__ = ["EVENT_TIMEOUT", "MAX_EVENTS", "MAX_RATE", "EventRefused", "Events", "Subscription"]
