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

Late answers slow a census down, never stop it: Stage frames that come for a query already
closed, at its first ``LATE_QUORUM`` stages (the start of a late joiner's answer, which stray
frames hardly ever form), tell how late answers come (a busy joiner, a loaded bus), and the
census then waits that much longer (and half as much more) before it closes a query or reuses
an epoch (``slack``, up to ``SLACK_MAX``). The slack halves every ``SLACK_HALF_LIFE`` seconds
in which no answer comes late. A query that closed with no answer at all is opened again when
its answers come after all (unless its epoch carried another query since).

Stray or forged Stage frames cost bounded work: an answer counts only when it is complete (a
joiner with the prefix answers every stage after it), an incomplete one is asked again at
most ``RETRIES`` times and ``RETRY_BUDGET`` times per census, and one census sends at most
``MAX_QUERIES`` queries; what is cut is counted and logged, and the joiners not found yet are
found by the next census (they knock again).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

from ups import _canproto as p

log = logging.getLogger("ups.can_ecb")

FIRST = 0.25  #: a query closes no sooner than 4 round trips (at most this) after it was sent,
#: the round trip being the time from a query to its first answer, averaged; and only once ...
QUIET = 0.04  #: ... no answer came for this long (the answers of one query come in bursts) ...
LONGEST = 2.0  #: ... or this long after it was sent, whichever comes first
FIRST_MIN = 0.03
QUARANTINE = 0.04  #: an epoch is not reused for this long after its query closed
RETRIES = 3  #: a prefix whose answers keep arriving incomplete is queried at most this often
RETRY_BUDGET = 64  #: ... and one census asks again at most this many times in all
MAX_QUERIES = 1024  #: queries of one census (8 per TxNode): past it the census ends, counted
SLACK_MAX = 4.0  #: seconds: the longest wait for late answers that the census adapts to
LATE_QUORUM = 4  #: late Stage frames at a closed query's first stages that show lateness
SLACK_HALF_LIFE = 2.0  #: seconds without a late answer in which the slack halves
LOG_GAP = 1.0  #: the census's warnings (late, incomplete or cut answers) at most this often


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
        self._retries = 0  # queries asked again in this census
        self._sent = 0  # queries sent in this census
        self._again = False
        self._rtt = 0.025  # the round trip from a query to its first answer, averaged
        self._slack = 0.0  # the slack when an answer last came late, at ``_late_at``
        self._late_at = 0.0
        self._last_sent = [-1.0] * p.EPOCHS  # epoch -> when its last query was sent
        self._last_prefix = [0] * p.EPOCHS  # epoch -> the prefix length of its last query
        self._late_stages: list[set[int]] = [set() for _ in range(p.EPOCHS)]  # since it closed
        self._unanswered: dict[int, _Query] = {}  # epoch -> its last query, closed unanswered
        self._timer: asyncio.TimerHandle | None = None
        self._logged = -LOG_GAP
        self._unlogged: collections.Counter[str] = collections.Counter()
        self.counters = dict.fromkeys(
            ("censuses", "knocks", "queries", "stages", "late_stages", "reopened", "incomplete",
             "retries", "cut"),
            0,
        )  # fmt: skip

    @property
    def running(self) -> bool:
        return bool(self._open or self._waiting)

    def knock(self) -> None:
        """A joiner asked: start a census, or another one after the current one (however many
        Knocks come meanwhile: they are served in turn, one census each time)."""
        self.counters["knocks"] += 1
        if self.running:
            self._again = True
            return
        self.counters["censuses"] += 1
        self._tries.clear()
        self._retries = self._sent = 0
        self._waiting.append(())
        self._pump()

    def on_stage(self, msg: p.Stage) -> None:
        now = asyncio.get_running_loop().time()
        query = self._open.get(msg.epoch)
        if query is None:
            query = self._reopen(msg, now)
        offset = -1 if query is None else msg.stage - len(query.prefix)
        if query is None or offset < 0:
            self.counters["late_stages"] += 1
            if query is None:
                self._late_stage(msg, now)
            return
        self.counters["stages"] += 1
        if not query.answered:
            query.answered = True
            self._rtt += (now - query.sent - self._rtt) / 4
        while len(query.stages) <= offset:
            query.stages.append(set())
        query.stages[offset].add(msg.nibble)
        query.last = now

    def _late_stage(self, msg: p.Stage, now: float) -> None:
        """A Stage for the query its epoch last carried, which has closed: once the query's
        first ``LATE_QUORUM`` stages came late, it was a joiner's late answer (not a stray
        frame), and the census waits longer for answers."""
        sent, first = self._last_sent[msg.epoch], self._last_prefix[msg.epoch]
        if sent < 0 or now - sent > LONGEST + SLACK_MAX or msg.stage < first:
            return
        late = self._late_stages[msg.epoch]
        late.add(msg.stage)
        wanted = range(first, min(first + LATE_QUORUM, p.NIBBLES))
        if len(late) >= len(wanted) and all(stage in late for stage in wanted):
            late.clear()
            self._late(now - sent)

    def _reopen(self, msg: p.Stage, now: float) -> _Query | None:
        """A Stage for a query that closed with no answer at all, and whose epoch carried no
        query since: its answers come late, not never. Open it again and hear them out."""
        query = self._unanswered.get(msg.epoch)
        if query is None or msg.stage < len(query.prefix):
            return None
        del self._unanswered[msg.epoch]
        self.counters["reopened"] += 1
        self._late(now - query.sent)
        query.sent = now  # a window of its own from now on
        self._open[msg.epoch] = query
        self._arm(now)
        return query

    @property
    def slack(self) -> float:
        """How much longer than usual the census waits for answers now: 1.5 times the
        lateness of the latest late answer, halving every ``SLACK_HALF_LIFE`` s since."""
        if self._slack == 0.0:
            return 0.0
        age = asyncio.get_running_loop().time() - self._late_at
        slack = self._slack * math.exp2(-age / SLACK_HALF_LIFE)
        if slack < FIRST_MIN:
            self._slack = 0.0
        return slack

    def _late(self, delay: float) -> None:
        """An answer came ``delay`` s after its query, which had closed: wait that long (and a
        half more) from now on, so that such answers are heard."""
        slack = min(SLACK_MAX, 1.5 * delay)
        if slack > self.slack:
            self._slack = slack
            self._late_at = asyncio.get_running_loop().time()
        self._note("late")

    def _note(self, what: str) -> None:
        """Count a kind of trouble for the next warning (at most one per ``LOG_GAP`` s)."""
        self._unlogged[what] += 1
        now = asyncio.get_running_loop().time()
        if now - self._logged < LOG_GAP:
            return
        self._logged = now
        said = []
        for kind, n in sorted(self._unlogged.items()):
            if kind == "late":
                said.append(f"{n} answers came late (waiting up to {self.slack:.2f} s now)")
            elif kind == "incomplete":
                said.append(f"{n} answers were incomplete (frames lost, or a node answers what "
                            "it should not)")  # fmt: skip
            else:
                said.append(f"{n} branches were cut (over {MAX_QUERIES} queries in a census)")
        self._unlogged.clear()
        log.warning("census: %s", "; ".join(said))

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._open.clear()
        self._waiting.clear()
        self._unanswered.clear()

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
            self._last_sent[epoch] = now
            self._last_prefix[epoch] = len(prefix)
            self._late_stages[epoch].clear()
            self._unanswered.pop(epoch, None)
            self.counters["queries"] += 1
            self._sent += 1
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
        first = max(min(FIRST, max(FIRST_MIN, 4 * self._rtt)), self.slack)
        quiet = max(self._quiet, self.slack / 4)
        return min(max(query.sent + first, query.last + quiet), query.sent + LONGEST + self.slack)

    def _tick(self) -> None:
        self._timer = None
        now = asyncio.get_running_loop().time()
        for epoch, query in list(self._open.items()):
            if now >= self._closes_at(query):
                del self._open[epoch]
                self._free_at[epoch] = now + max(self._quarantine, self.slack / 2)
                if not query.stages:
                    self._unanswered[epoch] = query
                self._conclude(query)
        self._pump()

    def _conclude(self, query: _Query) -> None:
        """Read a closed query's answers (docs/protocol.md, *Joining*)."""
        stages = query.stages
        if not stages:  # nobody has this prefix (any more)
            return
        if len(query.prefix) + len(stages) < p.NIBBLES or not all(stages):
            # A joiner with this prefix answers every stage after it: frames were lost, or
            # came from a node that should not answer. Ask again from what is certain.
            self.counters["incomplete"] += 1
            self._note("incomplete")
            certain = list(query.prefix)
            for nibbles in stages:
                if len(nibbles) != 1:
                    break
                certain.extend(nibbles)
            self._retry(tuple(certain))
            return
        prefix = list(query.prefix)
        leaves: list[int] = []
        for nibbles in stages:
            if len(nibbles) == 1:
                prefix.extend(nibbles)
                continue
            for nib in sorted(nibbles):  # several joiners: a query for each branch
                child = (*prefix, nib)
                if len(child) == p.NIBBLES:
                    leaves.append(p.id_of(child))
                else:
                    self._follow(child)
            break
        else:
            leaves.append(p.id_of(tuple(prefix)))
        if leaves:
            self._found(leaves)

    def _follow(self, prefix: tuple[int, ...]) -> None:
        """Query ``prefix`` in this census, unless the census has sent all it may."""
        if self._sent + len(self._waiting) >= MAX_QUERIES:
            self.counters["cut"] += 1
            self._note("cut")
            return
        self._waiting.append(prefix)

    def _retry(self, prefix: tuple[int, ...]) -> None:
        tries = self._tries.get(prefix, 0) + 1
        if tries <= RETRIES and self._retries < RETRY_BUDGET:
            self._tries[prefix] = tries
            self._retries += 1
            self.counters["retries"] += 1
            self._follow(prefix)
