"""The census: how the CAN-ECB learns the 64-bit ids of every node that wants to join.

A walk over the tree of the joiners' ids, nibble by nibble, in which many joiners are found at
once. The CAN-ECB asks a *query* (a prefix, in an epoch) and every joiner whose id starts with
that prefix answers with all its remaining nibbles, one data-less Stage frame each. Joiners
that share a nibble send identical frames, so they never disturb each other on a real bus.
When the answers stop coming, the CAN-ECB reads them stage by stage:

- one nibble at every stage: exactly one joiner has that prefix, and its whole id is known;
- several nibbles at stage s: the prefix is known up to s; each nibble heard there opens a
  query of its own (stages after s mix several ids and are ignored);
- no nibble at stage s (frames were lost): the prefix up to s is queried again.

Up to 16 queries are open at once, each in an epoch of its own. An epoch is reused only after
``QUARANTINE`` s, so that a late answer is rarely taken for an answer to another query; when
one is, it costs a query nobody answers, or an offer nobody claims (the CAN-ECB offers a
TxNode to each id found, and assigns it only when the node claims it). The
whole census costs each joiner one Stage frame per nibble and per branching on its path:
linear in the number of joiners.
"""

from __future__ import annotations

import asyncio
import collections
from collections.abc import Callable
from dataclasses import dataclass, field

from ups import _canproto as p

FIRST = 0.25  #: a query closes no sooner than 4 round trips (at most this) after it was sent,
#: the round trip being the time from a query to its first answer, averaged; and only once ...
QUIET = 0.04  #: ... no answer came for this long (the answers of one query come in bursts) ...
LONGEST = 2.0  #: ... or this long after it was sent, whichever comes first
FIRST_MIN = 0.03
QUARANTINE = 0.04  #: an epoch is not reused for this long after its query closed
RETRIES = 3  #: a prefix whose answers keep arriving incomplete is queried at most this often


@dataclass
class _Query:
    prefix: tuple[int, ...]
    sent: float
    last: float
    stages: list[set[int]] = field(default_factory=list)  # index: stage - len(prefix)
    answered: bool = False


class Census:
    """Runs censuses on request (``knock``); ``found(node_ids)`` gets every id it completes."""

    def __init__(
        self,
        send: Callable[[p.Management], None],
        found: Callable[[list[int]], None],
        *,
        quiet: float = QUIET,
        quarantine: float = QUARANTINE,
    ) -> None:
        self._send = send
        self._found = found
        self._quiet = quiet
        self._quarantine = quarantine
        self._open: dict[int, _Query] = {}  # epoch -> query
        self._waiting: collections.deque[tuple[int, ...]] = collections.deque()
        self._free_at = [0.0] * p.EPOCHS
        self._next_epoch = 0
        self._tries: dict[tuple[int, ...], int] = {}
        self._again = False
        self._rtt = 0.025  # the round trip from a query to its first answer, averaged
        self._timer: asyncio.TimerHandle | None = None
        self.counters = dict.fromkeys(("censuses", "queries", "stages", "late_stages"), 0)

    @property
    def running(self) -> bool:
        return bool(self._open or self._waiting)

    def knock(self) -> None:
        """A joiner asked: start a census, or another one after the current one."""
        if self.running:
            self._again = True
            return
        self.counters["censuses"] += 1
        self._tries.clear()
        self._waiting.append(())
        self._pump()

    def on_stage(self, msg: p.Stage) -> None:
        query = self._open.get(msg.epoch)
        offset = -1 if query is None else msg.stage - len(query.prefix)
        if query is None or offset < 0:
            self.counters["late_stages"] += 1
            return
        self.counters["stages"] += 1
        now = asyncio.get_running_loop().time()
        if not query.answered:
            query.answered = True
            self._rtt += (now - query.sent - self._rtt) / 4
        while len(query.stages) <= offset:
            query.stages.append(set())
        query.stages[offset].add(msg.nibble)
        query.last = now

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._open.clear()
        self._waiting.clear()

    # --- internals -------------------------------------------------------------------------

    def _pump(self) -> None:
        """Send waiting queries while epochs are free; arm the timer for what comes next."""
        now = asyncio.get_running_loop().time()
        while self._waiting:
            epoch = self._free_epoch(now)
            if epoch is None:
                break
            prefix = self._waiting.popleft()
            self._open[epoch] = _Query(prefix, now, now)
            self.counters["queries"] += 1
            self._send(p.Query(epoch, prefix) if prefix else p.Census(epoch))
        if not self.running and self._again:
            self._again = False
            self.knock()
            return
        self._arm(now)

    def _free_epoch(self, now: float) -> int | None:
        for i in range(p.EPOCHS):
            epoch = (self._next_epoch + i) % p.EPOCHS
            if epoch not in self._open and self._free_at[epoch] <= now:
                self._next_epoch = (epoch + 1) % p.EPOCHS
                return epoch
        return None

    def _arm(self, now: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        times = [self._closes_at(q) for q in self._open.values()]
        if self._waiting:
            times += [t for e, t in enumerate(self._free_at) if e not in self._open]
        if times:
            delay = max(0.0, min(times) - now)
            self._timer = asyncio.get_running_loop().call_later(delay, self._tick)

    def _closes_at(self, query: _Query) -> float:
        first = min(FIRST, max(FIRST_MIN, 4 * self._rtt))
        return min(max(query.sent + first, query.last + self._quiet), query.sent + LONGEST)

    def _tick(self) -> None:
        self._timer = None
        now = asyncio.get_running_loop().time()
        for epoch, query in list(self._open.items()):
            if now >= self._closes_at(query):
                del self._open[epoch]
                self._free_at[epoch] = now + self._quarantine
                self._conclude(query)
        self._pump()

    def _conclude(self, query: _Query) -> None:
        prefix = list(query.prefix)
        leaves: list[int] = []
        for nibbles in query.stages:
            if len(nibbles) == 1:
                prefix.extend(nibbles)
                continue
            if not nibbles:  # frames were lost: ask again from what is certain
                self._retry(tuple(prefix))
                break
            for nib in sorted(nibbles):
                child = (*prefix, nib)
                if len(child) == p.NIBBLES:
                    leaves.append(p.id_of(child))
                else:
                    self._waiting.append(child)
            break
        else:
            if len(prefix) == p.NIBBLES:
                leaves.append(p.id_of(tuple(prefix)))
            elif len(prefix) > len(query.prefix):  # the answers stopped short
                self._retry(tuple(prefix))
            # else: nobody answered; nobody has this prefix (any more)
        if leaves:
            self._found(leaves)

    def _retry(self, prefix: tuple[int, ...]) -> None:
        tries = self._tries.get(prefix, 0) + 1
        if tries <= RETRIES:
            self._tries[prefix] = tries
            self._waiting.append(prefix)
