"""The election between CAN-ECBs (broker/_election.py), run by a simulated bus in virtual time.

The state machine starts and stops two or three CAN-ECBs with random instances and recovery
windows, lets time pass, and delivers every frame to every other running CAN-ECB after a
random delay of at most ``DELAY``, each one possibly reordered with others and, while the
medium is lossy, possibly lost. The CAN-ECBs are the real ``Election`` objects that ``CanEcb``
drives; only the bus is simulated. Checked at every moment (just before and just after each
event, the state being constant in between):

- a serving CAN-ECB stands by only on the Serving of a lower instance, a candidate only on a
  Serving or a lower Hello: never on a Probe;
- exactly one CAN-ECB is active (candidate or serving) within ``BOUND`` of the last
  disturbance (a lost frame, a start, a stop) -- the bound docs/protocol.md states;
- with no frame lost for ``BOUND``: more than one is active only within ``OVERLAP`` after one
  starts or takes over (a newcomer is a candidate until it hears the one that serves), and
  none is only within ``TAKEOVER + DELAY`` after one stops.

"At most one active at every moment" cannot hold on any bus that can lose frames: two
CAN-ECBs that hear nothing of each other cannot tell the bus from one they are alone on, and
each must then serve. Nor with any delay: two that start together are both candidates until
their Hellos arrive. So the invariants bound when and how long it can happen.

``test_the_machine_finds_the_old_deadlock`` runs the same machine against the rules before
issue 29 (tests/_old_election.py) and expects it to fail.
"""

from __future__ import annotations

import collections
import heapq
import itertools
import math
from collections.abc import Callable, Sequence
from typing import Protocol

import pytest
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    rule,
    run_state_machine_as_test,
)

from ups._canproto import (
    CLAIM,
    PUB_BIND,
    SUB_BIND,
    UNSUB,
    Assign,
    Bind,
    Census,
    EtagsFull,
    Failed,
    Grant,
    Hello,
    Knock,
    Limit,
    Management,
    Offer,
    Probe,
    Query,
    Request,
    Serving,
    TxNodesFull,
)
from ups.broker import _election as e
from ups.broker._election import Election, Frame, Role

from ._old_election import OldElection

DELAY = 0.25  #: the simulated bus delivers every frame within this long
OVERLAP = e.MAX_CANDIDACY + e.SERVING_GAP + 2 * DELAY
BOUND = 14.0  #: docs/protocol.md, Timers: "one serving"
assert BOUND >= e.BEAT + OVERLAP  # the reasoning in broker/_election.py's docstring
EPSILON = 1e-9  #: times are sums of floats
MAX_EVENTS = 20_000  #: per rule: more means the election loops in virtual time


class Candidate(Protocol):
    """What the machine needs of an election (``Election``, or the old rules)."""

    instance: int
    candidacy: float

    @property
    def role(self) -> Role: ...

    @property
    def active(self) -> bool: ...

    @property
    def deadline(self) -> float | None: ...

    def start(self, now: float) -> list[Frame]: ...

    def heard(self, msg: Management, now: float) -> list[Frame]: ...

    def tick(self, now: float) -> list[Frame]: ...


Make = Callable[[int, float], Candidate]

delays = st.one_of(st.just(0.0), st.just(DELAY), st.floats(0.0, DELAY))
instances = st.integers(0, (1 << 64) - 1)
recoveries = st.sampled_from([0.0, 0.2, 0.5, 1.5, 2.0, 3.0])
waits = st.one_of(
    st.sampled_from([0.001, 0.05, 0.3, 1.0, 2.0, 4.0, 8.0, 20.0]), st.floats(0.0, 6.0)
)


class ElectionMachine(RuleBasedStateMachine):
    make: Make = Election
    slots = 3
    lossless = False  #: the medium never loses a frame
    seniority = True  #: check that a newcomer does not displace the one that serves

    def __init__(self) -> None:
        super().__init__()
        self.now = 0.0
        self.ecbs: list[Candidate | None] = [None] * self.slots
        self.lives = [0] * self.slots  # which run of each slot a frame is addressed to
        self.queue: list[tuple[float, int, int, int, Management]] = []  # (at, seq, slot, life, _)
        self.seq = itertools.count()
        self.lossy = False
        self.last_loss = -math.inf
        self.last_start = -math.inf  # external starts, and takeovers
        self.last_change = -math.inf  # starts and stops (the disturbances besides loss)
        self.last_stop = -math.inf
        self.used: set[int] = set()
        self.activated: dict[int, tuple[float, float]] = {}  # instance -> last Hello, candidacy
        self.serving_since: dict[int, float] = {}  # instance -> when it last began to serve
        self.draw: Callable[[st.SearchStrategy[object]], object] | None = None
        self.trace: collections.deque[str] = collections.deque(maxlen=40)  # for failures

    # --- the medium -------------------------------------------------------------------------

    def _broadcast(self, sender: int, frames: Sequence[Management]) -> None:
        for frame in frames:
            if isinstance(frame, Hello):  # a start, or a takeover
                self.last_start = self.now
                ecb = self.ecbs[sender]
                assert ecb is not None
                self.activated[frame.instance] = (self.now, ecb.candidacy)
            for slot, ecb in enumerate(self.ecbs):
                if slot == sender or ecb is None:
                    continue
                if self.lossy and self._draw(st.booleans()):
                    self.last_loss = self.now
                    self._note(f"{frame} from {sender} to {slot} lost")
                    continue
                delay = float(self._draw(delays)) if self.draw else DELAY  # type: ignore[arg-type]
                item = (self.now + delay, next(self.seq), slot, self.lives[slot], frame)
                heapq.heappush(self.queue, item)

    def _draw(self, strategy: st.SearchStrategy[object]) -> object:
        return False if self.draw is None else self.draw(strategy)

    def _next_event(self) -> float:
        deadlines = [d for ecb in self.ecbs if ecb is not None and (d := ecb.deadline) is not None]
        queued = [self.queue[0][0]] if self.queue else []
        return min([*deadlines, *queued], default=math.inf)

    def _advance(self, until: float) -> None:
        for _ in range(MAX_EVENTS):
            at = max(self._next_event(), self.now)
            if at > until:
                self.now = until
                self._check()
                return
            self.now = at
            self._check()  # the state held until now
            self._one_event()
            self._check()
        raise AssertionError(f"more than {MAX_EVENTS} events before {until:.3f} s")

    def _one_event(self) -> None:
        if self.queue and self.queue[0][0] <= self.now:
            _, _, slot, life, frame = heapq.heappop(self.queue)
            ecb = self.ecbs[slot]
            if ecb is None or life != self.lives[slot]:
                return  # sent to a run that has stopped
            before = ecb.role
            answer = ecb.heard(frame, self.now)
            self._note(f"{slot} heard {frame}: {before.value} -> {ecb.role.value}, sent {answer}")
            self._served(ecb, before)
            self._check_stand_down(ecb, before, frame)
            self._broadcast(slot, answer)
            return
        for slot, ecb in enumerate(self.ecbs):
            deadline = None if ecb is None else ecb.deadline
            if ecb is not None and deadline is not None and deadline <= self.now:
                before = ecb.role
                frames = ecb.tick(self.now)
                self._note(f"{slot} tick: {before.value} -> {ecb.role.value}, sent {frames}")
                self._served(ecb, before)
                assert not (before is Role.SERVING and ecb.role is Role.STANDBY)
                self._broadcast(slot, frames)
                return
        raise AssertionError("an event was due and none happened")

    # --- what is checked --------------------------------------------------------------------

    def _check_stand_down(self, ecb: Candidate, before: Role, frame: Frame) -> None:
        if ecb.role is not Role.STANDBY or before is Role.STANDBY:
            return
        lower = isinstance(frame, Hello | Serving | Probe) and frame.instance < ecb.instance
        if before is Role.SERVING:
            assert isinstance(frame, Serving) and lower, f"a serving one stood by on {frame}"
            if self.seniority and self.now - self.last_loss > BOUND:
                # the first to serve stays, unless the newcomer's candidacy ended before the
                # answer to its Hello could come (then the lower instance stays)
                newer = self.activated[frame.instance][0] >= self.serving_since[ecb.instance]
                assert not newer or self._hasty(frame.instance), (
                    f"a serving one stood by for {frame}, which came later: {self._roles()}"
                )
        else:
            assert isinstance(frame, Serving) or (isinstance(frame, Hello) and lower), (
                f"a candidate stood by on {frame}"
            )

    def _served(self, ecb: Candidate, before: Role) -> None:
        if ecb.role is Role.SERVING and before is not Role.SERVING:
            self.serving_since[ecb.instance] = self.now

    def _hasty(self, instance: int) -> bool:
        """A newcomer that served before the answer to its Hello could come."""
        since, candidacy = self.activated[instance]
        newcomer = self.now - since <= OVERLAP + EPSILON
        return newcomer and candidacy < e.SERVING_GAP + 2 * DELAY + EPSILON

    def _check(self) -> None:
        running = [ecb for ecb in self.ecbs if ecb is not None]
        if not running:
            return
        active = sum(ecb.active for ecb in running)
        disturbed = self.now - max(self.last_loss, self.last_change)
        assert active == 1 or disturbed <= BOUND + EPSILON, (
            f"{active} active {disturbed:.2f} s after the last disturbance: {self._roles()}"
        )
        if self.now - self.last_loss <= BOUND + EPSILON:
            return
        if active > 1:
            assert self.now - self.last_start <= OVERLAP + EPSILON, (
                f"{active} active {self.now - self.last_start:.2f} s after a start: {self._roles()}"
            )
        if active == 0:
            assert self.now - self.last_stop <= e.TAKEOVER + DELAY + EPSILON, (
                f"none active {self.now - self.last_stop:.2f} s after a stop: {self._roles()}"
            )

    def _roles(self) -> str:
        roles = ", ".join(
            "-" if ecb is None else f"{ecb.instance:x}:{ecb.role.value}" for ecb in self.ecbs
        )
        return f"{roles} at {self.now:.3f} s; last events:\n" + "\n".join(self.trace)

    def _note(self, what: str) -> None:
        self.trace.append(f"{self.now:9.3f} {what}")

    # --- rules ------------------------------------------------------------------------------

    @initialize(instance=instances, recovery=recoveries, data=st.data())
    def first(self, instance: int, recovery: float, data: st.DataObject) -> None:
        self.start(instance, recovery, data)

    @rule(instance=instances, recovery=recoveries, data=st.data())
    def start(self, instance: int, recovery: float, data: st.DataObject) -> None:
        """A CAN-ECB starts (if a place is free)."""
        if None not in self.ecbs or instance in self.used:
            return
        slot = self.ecbs.index(None)
        self.used.add(instance)
        ecb = type(self).make(instance, recovery)
        self.ecbs[slot] = ecb
        self.lives[slot] += 1
        self.last_change = self.now
        self.draw = data.draw
        frames = ecb.start(self.now)
        self._note(f"{slot} starts as {instance:x} (recovery {recovery} s), sent {frames}")
        self._broadcast(slot, frames)
        self._check()

    @rule(which=st.integers(0, 2), active=st.booleans())
    def stop(self, which: int, active: bool) -> None:
        """A CAN-ECB stops: any, or one that is active (what takeovers are for)."""
        slots = [
            slot
            for slot, ecb in enumerate(self.ecbs)
            if ecb is not None and (ecb.active or not active)
        ]
        if not slots:
            return
        slot = slots[which % len(slots)]
        self.ecbs[slot] = None
        self.last_change = self.last_stop = self.now
        self._note(f"{slot} stops")
        self._check()

    @rule(lossy=st.booleans())
    def medium(self, lossy: bool) -> None:
        self.lossy = lossy and not self.lossless
        self._note("the medium loses frames" if lossy else "the medium loses none")

    @rule(seconds=waits, data=st.data())
    def wait(self, seconds: float, data: st.DataObject) -> None:
        self.draw = data.draw
        self._advance(self.now + seconds)

    @invariant()
    def checked(self) -> None:
        self._check()

    def teardown(self) -> None:
        """The medium stops losing frames: within BOUND exactly one serves, and stays."""
        self.lossy = False
        self.draw = None  # every frame takes DELAY
        if any(ecb is not None for ecb in self.ecbs):
            self._advance(self.now + 3 * BOUND)
            assert sum(ecb is not None and ecb.active for ecb in self.ecbs) == 1


def _machine(
    make: Make, slots: int, *, lossless: bool = False, seniority: bool = True
) -> type[ElectionMachine]:
    attributes = {
        "make": staticmethod(make),
        "slots": slots,
        "lossless": lossless,
        "seniority": seniority,
    }
    return type(f"Machine{slots}", (ElectionMachine,), attributes)


#: enough to find the old deadlock within a few hundred examples (checked below); the suite
#: stays quick on a loaded machine, and the saved database replays what failed once
SETTINGS = settings(
    max_examples=300,
    stateful_step_count=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)

TestTwoCanEcbs = _machine(Election, 2).TestCase
TestTwoCanEcbs.settings = SETTINGS
TestThreeCanEcbs = _machine(Election, 3).TestCase
TestThreeCanEcbs.settings = settings(SETTINGS, max_examples=400)


#: when a node sends a request again while it has no answer (ups/_canbinding.py: 50 ms,
#: doubling to 1 s; it gives up after 5 s)
RETRIES = (0.05, 0.1, 0.2, 0.4, 0.8, 1.0, 1.0, 1.0)


class AnsweringMachine(ElectionMachine):
    """The same bus with a node's requests (SUB_BIND), sent again as a node does until an answer
    was sent: every CAN-ECB hears each one after its own delay; a serving one answers it at once
    (a Bind), a candidate when its candidacy ends (it holds it, as in recovery), one that stands
    by watches it. CAN-ECBs start at any time and none stops, and the medium loses nothing: then
    a standing-by one never takes over for a request it heard unanswered (the answer time is
    longer than a candidacy plus two delays), so none is ever wary."""

    slots = 2
    lossless = True

    def __init__(self) -> None:
        super().__init__()
        self.uids = itertools.count(1)
        self.sends: list[tuple[float, int, int]] = []  # (at, uid, tries): the node's next send
        self.held: dict[int, list[int]] = {}  # slot -> the requests a candidate holds
        self.answered: set[int] = set()

    def stop(self) -> None:  # not a rule here: nobody stops
        raise AssertionError("not a rule of this machine")

    @rule()
    def request(self) -> None:
        """A node asks for a channel's etag."""
        heapq.heappush(self.sends, (self.now, next(self.uids), 0))

    def _next_event(self) -> float:
        return min(super()._next_event(), self.sends[0][0] if self.sends else math.inf)

    def _send(self) -> None:
        _, uid, tries = heapq.heappop(self.sends)
        if uid in self.answered:
            return
        for slot, ecb in enumerate(self.ecbs):
            if ecb is not None:
                delay = float(self._draw(delays)) if self.draw else DELAY  # type: ignore[arg-type]
                frame = Request(SUB_BIND, 1, uid)
                item = (self.now + delay, next(self.seq), slot, self.lives[slot], frame)
                heapq.heappush(self.queue, item)
        if tries < len(RETRIES):
            heapq.heappush(self.sends, (self.now + RETRIES[tries], uid, tries + 1))

    def _broadcast(self, sender: int, frames: Sequence[Management]) -> None:
        self.answered.update(f.uid for f in frames if isinstance(f, Bind))
        super()._broadcast(sender, frames)

    def _one_event(self) -> None:
        if self.sends and self.sends[0][0] <= self.now:
            self._send()
            return
        if self.queue and self.queue[0][0] <= self.now and isinstance(self.queue[0][4], Request):
            _, _, slot, _, frame = heapq.heappop(self.queue)
            assert isinstance(frame, Request)
            ecb = self.ecbs[slot]
            assert isinstance(ecb, Election)
            self._note(f"{slot} ({ecb.role.value}) heard {frame}")
            if ecb.role is Role.STANDBY:
                ecb.asked(frame, self.now, held=True)
            elif ecb.role is Role.SERVING:
                self._broadcast(slot, [Bind(0x20, frame.value)])
            else:
                self.held.setdefault(slot, []).append(frame.value)
            return
        roles = [None if ecb is None else ecb.role for ecb in self.ecbs]
        super()._one_event()
        for slot, ecb in enumerate(self.ecbs):
            if ecb is None or ecb.role is roles[slot]:
                continue
            held = self.held.pop(slot, [])
            if ecb.role is Role.SERVING and roles[slot] is Role.CANDIDATE:
                self._broadcast(slot, [Bind(0x20, uid) for uid in held])  # its recovery ended

    def _check(self) -> None:
        super()._check()
        wary = [ecb for ecb in self.ecbs if isinstance(ecb, Election) and ecb.wary]
        assert not wary, f"a CAN-ECB took over for an unanswered request: {self._roles()}"


TestAnsweringCanEcbs = AnsweringMachine.TestCase
TestAnsweringCanEcbs.settings = SETTINGS


@pytest.mark.parametrize("slots", [2, 3])
def test_the_machine_finds_the_old_deadlock(slots: int) -> None:
    """The old rules (a standby's probe was a Serving, which a serving CAN-ECB took as a
    claim) fail this machine, even on a medium that loses nothing: two stand by for good."""
    with pytest.raises(AssertionError, match="none active"):
        run_state_machine_as_test(
            _machine(OldElection, slots, lossless=True, seniority=False),
            settings=settings(
                SETTINGS,
                max_examples=2000,
                phases=[Phase.generate],
                database=None,
                report_multiple_bugs=False,
                # the old rules fail in more than one way ("2 active" too); a fixed sequence
                # of examples finds this one every time (a random one found the other once)
                derandomize=True,
            ),
        )


# --- the rules one by one (docs/protocol.md, "More than one CAN-ECB") ---------------------------


def _serving(instance: int = 5, now: float = 0.0) -> Election:
    ecb = Election(instance, recovery=0.0)
    assert ecb.start(now) == [Hello(instance)]
    assert ecb.tick(now) == [Serving(instance)]  # the candidacy's end
    return ecb


def test_a_serving_one_answers_a_probe_and_never_stands_by_for_one() -> None:
    ecb = _serving()
    assert ecb.heard(Probe(0), 1.5) == [Serving(5)]
    for t in range(2, 200):  # a standing-by rival of the lowest instance, probing
        ecb.heard(Probe(0), float(t))
        ecb.tick(float(t))
    assert ecb.role is Role.SERVING


def test_answers_are_sent_once_a_second_and_one_due_sooner_waits() -> None:
    ecb = _serving()
    assert ecb.heard(Hello(7), 0.2) == [Serving(5)]  # the candidacy's Serving answered nobody
    assert ecb.heard(Probe(8), 0.5) == []  # within the gap: owed
    assert ecb.heard(Hello(9), 0.7) == []  # one Serving owed for both
    assert ecb.deadline == 0.2 + e.SERVING_GAP
    assert ecb.tick(0.2 + e.SERVING_GAP) == [Serving(5)]
    assert ecb.deadline == 0.2 + e.SERVING_GAP + e.BEAT  # nothing owed: the beat


def test_a_serving_one_beats_unasked() -> None:
    ecb = _serving()
    assert ecb.tick(e.BEAT - 0.01) == []
    assert ecb.tick(e.BEAT) == [Serving(5)]


def test_a_serving_one_stands_by_only_for_a_lower_serving() -> None:
    ecb = _serving()
    assert ecb.heard(Hello(0), 2.0) == [Serving(5)]
    assert ecb.heard(Serving(9), 3.0) == [Serving(5)]
    assert ecb.heard(Serving(5), 4.0) == []  # its own instance: not a rival
    assert ecb.role is Role.SERVING
    assert ecb.heard(Serving(4), 5.0) == [] and ecb.role is Role.STANDBY


def test_a_candidate_stands_by_for_any_serving_and_a_lower_hello() -> None:
    for frame, stands_by in [
        (Serving(9), True), (Hello(4), True), (Hello(9), False), (Probe(0), False)
    ]:  # fmt: skip
        ecb = Election(5, recovery=2.0)
        ecb.start(0.0)
        assert ecb.heard(frame, 0.5) == []
        assert (ecb.role is Role.STANDBY) == stands_by, frame


def test_standing_by_it_probes_and_only_hello_or_serving_keeps_it_so() -> None:
    ecb = _serving()
    ecb.heard(Serving(4), 1.0)
    assert ecb.deadline == 1.0 + e.PROBE
    assert ecb.tick(1.0 + e.PROBE) == [Probe(5)]
    ecb.heard(Serving(4), 3.0)
    ecb.heard(Probe(4), 3.5)  # a Probe keeps nobody standing by
    assert ecb.tick(3.0 + e.PROBE) == [Probe(5)]
    assert ecb.tick(3.0 + e.TAKEOVER) == [Hello(5)]  # silent for the takeover time
    assert ecb.role is Role.CANDIDATE


# --- a standing-by CAN-ECB watches that the one serving answers (issue 41) ----------------------

UID = 0x5EC0_0000_0000_0041


def _standing_by(instance: int = 5, now: float = 1.0) -> Election:
    ecb = Election(instance, recovery=e.MAX_CANDIDACY)
    ecb.start(now - 0.5 - e.MAX_CANDIDACY)  # (a clock started before 0)
    assert ecb.tick(now - 0.5) == [Serving(instance)]
    ecb.heard(Serving(0), now)  # a lower instance claims to serve (or a forger)
    assert ecb.role is Role.STANDBY and not ecb.wary and ecb.unanswered == 0
    return ecb


def _tick_until(ecb: Election, until: float) -> list[Frame]:
    """Every timer up to ``until``, as the bus would call them; the frames they sent."""
    frames: list[Frame] = []
    while (deadline := ecb.deadline) is not None and deadline <= until:
        frames += ecb.tick(deadline)
    return frames


def test_a_request_unanswered_for_the_answer_time_makes_it_serve_whatever_servings_say() -> None:
    ecb = _standing_by()
    ecb.asked(Request(SUB_BIND, 0x12, UID), 1.5, held=True)
    ecb.asked(Request(SUB_BIND, 0x12, UID), 2.5, held=True)  # asked again: the first time counts
    for t in (2.0, 3.0, 3.9):  # a Serving every second keeps nobody standing by any more
        ecb.heard(Serving(0), t)
    assert Hello(5) not in _tick_until(ecb, 1.5 + e.ANSWER - 0.01)
    assert _tick_until(ecb, 1.5 + e.ANSWER)[-1:] == [Hello(5)]
    assert ecb.role is Role.CANDIDATE and ecb.wary and ecb.unanswered == 1
    assert "no answer" in ecb.reason


@pytest.mark.parametrize(
    ("request_", "answer"),
    [
        (Knock(), Census(3)),
        (Knock(), Query(3, (1, 2))),
        (Knock(), Offer(4, 0xAB)),
        (Knock(), Assign(4, 0xAB)),
        (Knock(), TxNodesFull(0xAB)),
        (Knock(), Failed(0xAB)),
        (Request(SUB_BIND, 0x12, UID), Bind(0x20, UID)),
        (Request(PUB_BIND, 0x12, UID, 2), Bind(0x3000, UID)),
        (Request(PUB_BIND, 0x12, UID), EtagsFull(UID)),
        (Request(SUB_BIND, 0x12, UID), Failed(UID)),
        (Request(SUB_BIND, 0x12, UID), Limit(0x12, UID)),
    ],
)
def test_an_answer_heard_stops_the_watch(request_: Management, answer: Management) -> None:
    ecb = _standing_by()
    ecb.asked(request_, 1.5, held=True)
    ecb.heard(answer, 3.5)
    for t in (2.0, 3.0, 4.0, 5.0):
        ecb.heard(Serving(0), t)
    assert Hello(5) not in _tick_until(ecb, 6.0)
    assert ecb.role is Role.STANDBY and not ecb.wary


def test_an_answer_to_another_request_or_a_frame_that_asks_nothing_does_not() -> None:
    ecb = _standing_by()
    ecb.asked(Request(UNSUB, 0x12, UID + 1), 1.2, held=True)  # no answer due: not watched
    ecb.asked(Request(CLAIM, 0x12, 0xAB), 1.2, held=True)
    ecb.asked(Request(SUB_BIND, 0x12, UID), 1.5, held=True)
    ecb.heard(Bind(0x20, UID + 1), 2.0)  # another channel's
    ecb.heard(Grant(0x20, 0x12, 0x02), 2.1)
    ecb.heard(Serving(0), 3.0)
    assert _tick_until(ecb, 1.5 + e.ANSWER)[-1:] == [Hello(5)]


def test_an_answer_heard_just_before_its_request_counts_frames_may_cross() -> None:
    ecb = _standing_by()
    ecb.heard(Bind(0x20, UID), 1.5)
    ecb.asked(Request(SUB_BIND, 0x12, UID), 1.5 + e.EARLY, held=True)  # the answer came first
    ecb.heard(Census(1), 1.5)
    ecb.asked(Knock(), 1.5 + e.EARLY + 0.01)  # a later Knock: its own answer is due
    ecb.heard(Serving(0), 3.0)
    ecb.heard(Serving(0), 4.5)
    frames = _tick_until(ecb, 1.5 + e.EARLY + e.ANSWER)
    assert Hello(5) not in frames and ecb.role is Role.STANDBY
    assert _tick_until(ecb, 1.5 + e.EARLY + 0.01 + e.ANSWER)[-1:] == [Hello(5)]


def test_only_requests_heard_while_standing_by_are_watched() -> None:
    ecb = _serving()
    ecb.asked(Request(SUB_BIND, 0x12, UID), 0.5, held=True)  # it answers these itself
    ecb.heard(Serving(0), 1.0)
    ecb.heard(Serving(0), 3.0)
    assert Hello(5) not in _tick_until(ecb, 4.9)


def test_at_most_watched_requests_are_watched_the_oldest_first() -> None:
    ecb = _standing_by()
    for n in range(e.WATCHED + 10):
        ecb.asked(Request(SUB_BIND, 0x12, n), 1.5 + n * 1e-4, held=True)
    for n in range(1, e.WATCHED + 10):
        ecb.heard(Bind(0x20, n), 2.0)
    ecb.heard(Serving(0), 3.0)
    assert _tick_until(ecb, 1.5 + e.ANSWER)[-1:] == [Hello(5)]  # UID 0, the first, had none


def _wary(instance: int = 5) -> Election:
    """A CAN-ECB that caught another not answering, and serves again."""
    ecb = _standing_by(instance)
    ecb.asked(Knock(), 1.5)
    _tick_until(ecb, 1.5 + e.ANSWER)
    assert ecb.wary and ecb.role is Role.CANDIDATE
    return ecb


def test_a_wary_candidate_stands_by_for_nothing_and_serves_its_candidacy_out() -> None:
    ecb = _wary()
    start = 1.5 + e.ANSWER
    for frame in (Serving(0), Hello(0), Bind(0x20, UID), Serving(1)):
        assert ecb.heard(frame, start + 0.01) == []
        assert ecb.role is Role.CANDIDATE
    assert ecb.tick(start + e.MAX_CANDIDACY) == [Serving(5)]


def test_a_wary_serving_one_stands_by_only_for_a_lower_serving_backed_by_answers() -> None:
    ecb = _wary()
    now = 1.5 + e.ANSWER + e.MAX_CANDIDACY
    ecb.tick(now)
    assert ecb.role is Role.SERVING
    for t in range(1, 30):  # a forger's Serving, every 3 s or every second: no effect
        assert ecb.heard(Serving(0), now + t) == []  # not even an answer
        ecb.tick(now + t)
    now += 30
    assert ecb.role is Role.SERVING
    # another CAN-ECB's answer, but busy (a census): it serves on
    assert ecb.heard(Bind(0x20, UID), now, busy=True) == [Serving(5)]
    assert ecb.heard(Serving(0), now + 0.1, busy=True) == []
    assert ecb.role is Role.SERVING
    # an answer long before the Serving does not back it
    assert ecb.heard(Serving(0), now + e.BACKING + 0.2) == []
    assert ecb.role is Role.SERVING
    # an answer within BACKING of a lower Serving: another CAN-ECB serves and answers
    ecb.heard(Assign(3, 0xAB), now + e.BACKING + 0.5)
    assert ecb.role is Role.STANDBY and ecb.wary
    assert "answers what this one answers" in ecb.reason


def test_a_wary_serving_one_does_not_stand_by_for_a_higher_serving_with_answers() -> None:
    ecb = _wary()
    now = 1.5 + e.ANSWER + e.MAX_CANDIDACY
    ecb.tick(now)
    ecb.heard(Bind(0x20, UID), now + 1.0)
    assert ecb.heard(Serving(9), now + 1.5) == []  # owed: within the Serving gap of the last
    assert ecb.role is Role.SERVING


def test_a_wary_one_standing_by_catches_again() -> None:
    ecb = _wary()
    now = 1.5 + e.ANSWER + e.MAX_CANDIDACY
    ecb.tick(now)
    ecb.heard(Bind(0x20, UID), now + 0.5)
    ecb.heard(Serving(0), now + 1.0)
    assert ecb.role is Role.STANDBY
    ecb.asked(Request(PUB_BIND, 0x12, UID + 2), now + 1.5, held=True)
    ecb.heard(Serving(0), now + 2.5)
    assert _tick_until(ecb, now + 1.5 + e.ANSWER)[-1:] == [Hello(5)]
    assert ecb.role is Role.CANDIDATE and ecb.wary


def test_the_process_tests_use_the_answer_time_of_the_code() -> None:
    from . import test_forged_serving_processes as processes

    assert processes.ANSWER == e.ANSWER
    assert e.ANSWER > e.MAX_CANDIDACY  # longer than a serving CAN-ECB holds a request
    assert e.ANSWER + e.MAX_CANDIDACY < 5.0  # the node's request limit (ups/_canbinding.py)
