"""The election of libups-ecb (c/ups_ecb_elect.c) against the Python CAN-ECB's
(broker/_election.py): the same events (Hello, Serving and Probe of other instances, the
answers of another CAN-ECB, the requests a standing-by one watches, ticks) at the same times
give the same role and the same frames at every step.

The C runs alone, through ``ups_ecb_host_elect`` (a host-only entry of c/host/ups_ecb_host.c,
for tests only), so that no other part of the CAN-ECB speaks in between. Python's election runs
on seconds as floats; to compare at the timers' exact edges, where a sum of floats may land a
hair off, it runs here on integer milliseconds: its timer constants are set to the protocol's
values in ms (and ``WATCHED`` to the C library's bound) for the duration of a comparison. The
C's clock starts anywhere, near its wrap too.

Ticks come where the Python CAN-ECB calls its election (``deadline``), and at random times
besides (the C one ticks every few ms: a tick where nothing is due must do nothing).
"""

from __future__ import annotations

import contextlib
import ctypes
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.procs import sanitizer_env
from ups import _canproto as p
from ups._cnode import build
from ups.broker import _election as e
from ups.broker._cecb_lib import SOURCES, VARIANTS
from ups.broker._election import Election, Role

ROOT = Path(__file__).resolve().parent.parent
C_DIR = ROOT / "c"
ROLES = (Role.STOPPED, Role.CANDIDATE, Role.SERVING, Role.STANDBY)  # UPS_ECB_STOPPED, ...
NOTE_ROLE = 0x02
SAY_HELLO = 0x01  # UPS_ECB__SAY_HELLO
TICK, HEARD, ASKED, START, NEXT = 0, 1, 2, 3, 4  # ups_ecb_host_elect's what
NONE = 0xFFFF_FFFF  #: ups_ecb__elect_next: no timer runs
#: broker/_election.py's timers in ms (docs/protocol.md, Timers)
TIMERS_MS = {
    "SERVING_GAP": 1000, "PROBE": 2000, "TAKEOVER": 4000, "BEAT": 10000,
    "MAX_CANDIDACY": 2000, "ANSWER": 2500, "BACKING": 2000, "EARLY": 1000,
}  # fmt: skip
#: the timers that may start at an event (and the short candidacies of the tests)
EDGES = (*sorted(set(TIMERS_MS.values())), 100, 999)
ME = 0x5000_0000_0000_0000  #: the instance of the CAN-ECB under test
OTHERS = (0x1, 0x4FFF_FFFF_FFFF_FFFF, 0x5000_0000_0000_0001, (1 << 64) - 1, ME)


class _Config(ctypes.Structure):  # ups_ecb_config_t
    _fields_ = [("bitrate", ctypes.c_uint32), ("fd", ctypes.c_uint8),
                ("recovery_ms", ctypes.c_uint16), ("lease_s", ctypes.c_uint32),
                ("max_channels", ctypes.c_uint16), ("quota", ctypes.c_uint16 * 5)]  # fmt: skip


class _Frame(ctypes.Structure):  # ups_frame_t (its first 8 data bytes)
    _fields_ = [("id", ctypes.c_uint32), ("flags", ctypes.c_uint8), ("len", ctypes.c_uint8),
                ("data", ctypes.c_uint8 * 8)]  # fmt: skip


def _counter_names() -> list[str]:
    """ups_ecb_counters_t's fields, in order, from the header."""
    header = (C_DIR / "ups_ecb.h").read_text()
    body = header[: header.index("} ups_ecb_counters_t;")]
    body = body[body.rindex("typedef struct {") :]
    return re.findall(r"UPS_ECB_COUNTER_T (\w+);", body)


def load_lib(variant: str) -> ctypes.CDLL:
    """libups-ecb of ``variant`` (broker/c_ecb.py's: "full", or "asan" in a process that has
    the ASan runtime), built if needed, its calls declared."""
    lib = ctypes.CDLL(str(build(variant, targets=VARIANTS, sources=SOURCES)))
    vp, u32 = ctypes.c_void_p, ctypes.c_uint32
    lib.ups_ecb_host_size.restype = ctypes.c_size_t
    lib.ups_ecb_host_config.restype = ctypes.c_long
    lib.ups_ecb_host_config.argtypes = [ctypes.c_int]
    lib.ups_ecb_init.argtypes = [vp, ctypes.POINTER(_Config), ctypes.c_uint64]
    lib.ups_ecb_default_config.argtypes = [ctypes.POINTER(_Config)]
    lib.ups_ecb_host_elect.restype = ctypes.c_uint
    lib.ups_ecb_host_elect.argtypes = [vp, u32, ctypes.c_int, u32, ctypes.c_char_p,
                                       ctypes.c_uint, ctypes.c_int]  # fmt: skip
    lib.ups_ecb_tx_peek.restype = ctypes.POINTER(_Frame)
    lib.ups_ecb_tx_peek.argtypes = [vp]
    lib.ups_ecb_tx_pop.argtypes = [vp]
    lib.ups_ecb_role.argtypes = [vp]
    lib.ups_ecb_notes.restype = ctypes.c_uint
    lib.ups_ecb_notes.argtypes = [vp]
    lib.ups_ecb_counters.restype = ctypes.c_void_p
    lib.ups_ecb_counters.argtypes = [vp]
    return lib


@pytest.fixture(scope="module")
def lib() -> ctypes.CDLL:
    return load_lib("full")


@contextlib.contextmanager
def milliseconds(watched: int) -> Iterator[None]:
    """broker/_election.py on integer milliseconds, watching as many requests as the C."""
    values = {**TIMERS_MS, "WATCHED": watched}
    saved = {name: getattr(e, name) for name in values}
    for name, value in values.items():
        setattr(e, name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(e, name, value)


class CElection:
    """The C election, driven as the dispatcher drives it."""

    def __init__(self, lib: ctypes.CDLL, instance: int, recovery_ms: int, base: int) -> None:
        self.lib = lib
        self.base = base  # the C clock's reading at time 0
        self.ecb = ctypes.create_string_buffer(lib.ups_ecb_host_size())
        cfg = _Config()
        lib.ups_ecb_default_config(ctypes.byref(cfg))
        cfg.recovery_ms = recovery_ms
        assert lib.ups_ecb_init(self.ecb, ctypes.byref(cfg), instance) == 0
        self.names = _counter_names()
        width = lib.ups_ecb_host_config(7)
        self.counter_t = {2: ctypes.c_uint16, 4: ctypes.c_uint32, 8: ctypes.c_uint64}[width]

    def call(
        self, now: int, what: int, can_id: int = 0, data: bytes = b"", busy: bool = False
    ) -> int:
        clock = (self.base + now) & 0xFFFF_FFFF
        return int(
            self.lib.ups_ecb_host_elect(self.ecb, clock, what, can_id, data, len(data), int(busy))
        )

    def sent(self) -> list[tuple[int, bytes]]:
        frames = []
        while frame := self.lib.ups_ecb_tx_peek(self.ecb):
            f = frame.contents
            frames.append((f.id, bytes(f.data[: f.len])))
            self.lib.ups_ecb_tx_pop(self.ecb)
        return frames

    @property
    def role(self) -> Role:
        return ROLES[self.lib.ups_ecb_role(self.ecb)]

    def notes(self) -> int:
        return int(self.lib.ups_ecb_notes(self.ecb))

    def counter(self, name: str) -> int:
        array = self.counter_t * len(self.names)
        return int(array.from_address(self.lib.ups_ecb_counters(self.ecb))[self.names.index(name)])


@dataclass(frozen=True)
class Step:
    """One event at ``at`` ms: what (tick, heard, asked), its frame and busy."""

    at: int
    what: int
    msg: p.Management | None = None
    busy: bool = False


class Pair:
    """The Python election and the C one, fed the same events; each step compared."""

    def __init__(self, lib: ctypes.CDLL, recovery_ms: int, base: int) -> None:
        self.py = Election(ME, recovery_ms)
        self.c = CElection(lib, ME, recovery_ms, base)
        self.now = 0
        self.trace: list[str] = []
        self.frames: list[tuple[int, Any]] = []  #: (when, frame) the elections sent
        self.events = [0]  #: when things happened (timers may end from then on)

    def start(self) -> None:
        assert self.py.start(0) == [p.Hello(ME)]
        self.c.call(0, START)
        self.check("start", [], 0, Role.STOPPED)

    def check(self, what: str, frames: list[Any], verdict: int, before: Role) -> None:
        self.trace.append(f"{self.now:>7} {what}: {self.py.role.value} {frames}")
        self.frames += [(self.now, frame) for frame in frames]
        want_hello = any(isinstance(f, p.Hello) for f in frames)
        want = [p.encode(f) for f in frames if not isinstance(f, p.Hello)]
        context = "\n".join(self.trace[-30:])
        assert self.c.role is self.py.role, context
        assert self.c.sent() == want, context
        assert bool(verdict & SAY_HELLO) == want_hello, context
        assert bool(self.c.notes() & NOTE_ROLE) == (self.py.role is not before), context
        assert self.c.counter("unanswered_takeovers") == self.py.unanswered, context
        deadline = self.py.deadline  # and the next timer (ups_ecb__elect_next)
        want_next = NONE if deadline is None else max(int(deadline) - self.now, 0)
        assert self.c.call(self.now, NEXT) == want_next, context

    def tick(self, at: int) -> None:
        self.now = at
        before = self.py.role
        frames = self.py.tick(at)
        self.check("tick", frames, self.c.call(at, TICK), before)

    def advance(self, to: int) -> None:
        """Time passes to ``to``: ticks at the Python CAN-ECB's deadlines, and around every
        time a timer started at an event could end (where a C timer that Python lacks would
        fire)."""
        edges = {
            at + timer + d
            for at in self.events
            for timer in EDGES
            for d in (-1, 0, 1)
            if self.now < at + timer + d <= to
        }
        for _ in range(100_000):
            deadline = self.py.deadline
            due = [t for t in edges if t > self.now]
            if deadline is not None and deadline <= to:
                due.append(max(int(deadline), self.now))
            if not due:
                break
            self.tick(min(due))
        else:
            raise AssertionError("the Python election's deadline does not move")
        self.now = to

    def step(self, step: Step) -> None:
        self.advance(step.at)
        self.events.append(step.at)
        before = self.py.role
        if step.what == TICK:
            self.tick(step.at)
            return
        assert step.msg is not None
        can_id, data = p.encode(step.msg)
        if step.what == HEARD:
            frames = self.py.heard(step.msg, step.at, step.busy)
        else:
            frames = self.py.asked(step.msg, step.at)
        verdict = self.c.call(step.at, step.what, can_id, data, step.busy)
        self.check(f"{'heard' if step.what == HEARD else 'asked'} {step.msg}", frames, verdict,
                   before)  # fmt: skip


def run(
    lib: ctypes.CDLL, steps: list[Step], recovery_ms: int = 2000, base: int = 0, after: int = 30_000
) -> Pair:
    """Both elections through ``steps``, then ``after`` ms more of their timers."""
    with milliseconds(lib.ups_ecb_host_config(6)):
        pair = Pair(lib, recovery_ms, base)
        pair.start()
        for step in steps:
            pair.step(step)
        pair.advance(pair.now + after)
    return pair


# --- the events ----------------------------------------------------------------------------

UIDS = [*range(1, 20), (1 << 64) - 1]  # more than the full build watches (16)
uids = st.one_of(st.sampled_from(UIDS[:3]), st.sampled_from(UIDS))  # answers meet requests
#: TxNodes: Assigns meet binding requests (only those of TxNodes heard assigned are watched)
txnodes = st.one_of(st.sampled_from([3, 4]), st.integers(0, 0x7E))
claims = st.builds(
    lambda kind, instance: kind(instance),
    st.sampled_from([p.Hello, p.Serving, p.Serving, p.Probe]), st.sampled_from(OTHERS),
)  # fmt: skip
answers = st.one_of(
    st.builds(p.Census, st.integers(0, 15)),
    st.builds(lambda uid: p.Query(1, (uid & 0xF,)), uids),
    st.builds(p.Offer, st.integers(0, 0x7E), uids),
    st.builds(p.Assign, txnodes, uids),
    st.builds(p.Assign, txnodes, uids),
    st.builds(p.TxNodesFull, uids),
    st.builds(p.Failed, uids),
    st.builds(p.EtagsFull, uids),
    st.builds(p.Limit, st.integers(0, 0x7E), uids),
    st.builds(p.Bind, st.integers(0x10, 0x3FFF), uids),
    st.builds(p.Grant, st.just(0x10), st.just(3), st.just(5)),
    st.builds(p.Uses, st.booleans(), st.just(3), uids),
    st.builds(p.RosterEnd, st.just(3), st.just(0), st.just(True)),
)
requests = st.one_of(
    st.just(p.Knock()),
    st.builds(p.Request, st.sampled_from([p.SUB_BIND, p.PUB_BIND]), txnodes, uids),
    st.builds(
        lambda t, uid, c: p.Request(p.PUB_BIND, t, uid, c),
        txnodes,
        uids,
        st.integers(1, 4),
    ),
    st.builds(p.Request, st.sampled_from([p.UNSUB, p.CLAIM, p.CLAIM]), txnodes, uids),
    st.builds(p.Roster, st.integers(0, 0x7E), uids),
    st.builds(p.Stage, st.integers(0, 15), st.integers(0, 15), st.integers(0, 15)),
)
#: waits that land on the timers' edges, and between them
gaps = st.one_of(
    st.sampled_from([0, 0, 1, 999, 1000, 1001, 1500, 1999, 2000, 2001, 2500, 4000, 10_000]),
    st.integers(0, 6000),
)
events = st.one_of(
    st.tuples(st.just(HEARD), claims, st.booleans()),
    st.tuples(st.just(HEARD), answers, st.booleans()),
    st.tuples(st.just(ASKED), requests, st.just(False)),
    st.tuples(st.just(ASKED), requests, st.just(False)),
    st.tuples(st.just(TICK), st.none(), st.just(False)),
)
bases = st.one_of(st.just(0), st.just((1 << 32) - 3000), st.integers(0, (1 << 32) - 1))


@st.composite
def sequences(draw: st.DrawFn) -> list[Step]:
    steps, at = [], 0
    for _ in range(draw(st.integers(0, 60))):
        at += draw(gaps)
        what, msg, busy = draw(events)
        steps.append(Step(at, what, msg, busy))
    return steps


def comparison(examples: int) -> Callable[[ctypes.CDLL], None]:
    """The comparison over ``examples`` drawn sequences, of the library given."""

    @settings(max_examples=examples, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(steps=sequences(), recovery=st.sampled_from([100, 999, 1000, 2000, 3000]), base=bases)
    def compare(lib: ctypes.CDLL, steps: list[Step], recovery: int, base: int) -> None:
        run(lib, steps, recovery, base)

    return compare


def test_the_c_election_does_what_the_python_one_does(lib: ctypes.CDLL) -> None:
    comparison(200)(lib)


# --- the rules, one by one (each also compared step by step) ---------------------------------


def heard(at: int, msg: p.Management, busy: bool = False) -> Step:
    return Step(at, HEARD, msg, busy)


def asked(at: int, msg: p.Management) -> Step:
    return Step(at, ASKED, msg)


LOWER, HIGHER = 0x1, (1 << 64) - 1
HELD = Step(50, HEARD, p.Assign(3, 7))  #: TxNode 3 is held: its binding requests are watched
SERVE_AT = 2000  #: the candidacy's end with the default recovery


def test_a_lone_one_serves_and_beats(lib: ctypes.CDLL) -> None:
    pair = run(lib, [Step(SERVE_AT + 25_000, TICK)], after=0)
    assert pair.c.role is Role.SERVING
    assert [at for at, _ in pair.frames] == [2000, 12_000, 22_000]  # Serving, then beats


def test_a_candidate_stands_by_for_a_serving_and_a_lower_hello(lib: ctypes.CDLL) -> None:
    assert run(lib, [heard(500, p.Serving(HIGHER))], after=0).c.role is Role.STANDBY
    steps = [heard(500, p.Hello(HIGHER)), heard(550, p.Probe(LOWER))]
    assert run(lib, steps, after=0).c.role is Role.CANDIDATE
    pair = run(lib, [*steps, heard(600, p.Hello(LOWER))], after=3999)
    assert pair.c.role is Role.STANDBY  # a Probe at 2 s, not yet the takeover
    pair = run(lib, [*steps, heard(600, p.Hello(LOWER))], after=4000)
    assert pair.c.role is Role.CANDIDATE


def test_a_serving_one_answers_paced_and_stands_by_only_for_a_lower_serving(
    lib: ctypes.CDLL,
) -> None:
    steps = [heard(at, p.Probe(HIGHER)) for at in (2100, 2200, 2300, 3000)]  # paced: 2 Servings
    steps += [heard(3300, p.Hello(LOWER)), heard(3400, p.Serving(HIGHER))]
    pair = run(lib, steps, base=7, after=0)
    assert pair.c.role is Role.SERVING
    assert [at for at, _ in pair.frames] == [2000, 2100, 3100]  # Serving, 2 answers
    pair = run(lib, [*steps, heard(3500, p.Serving(LOWER))], after=0)
    assert pair.c.role is Role.STANDBY


def test_an_unanswered_request_makes_it_take_over_and_wary(lib: ctypes.CDLL) -> None:
    steps = [
        HELD,
        heard(100, p.Serving(LOWER)),  # stands by
        asked(1000, p.Request(p.SUB_BIND, 3, 42)),
        heard(1500, p.Serving(LOWER)),
        heard(2000, p.Bind(0x20, 41)),  # not its answer
        heard(3000, p.Serving(LOWER)),
        Step(3500, TICK),  # 2.5 s: takes over, wary
        heard(3600, p.Serving(LOWER)),  # a wary candidate stands by for nothing
    ]
    pair = run(lib, steps, after=0)
    assert pair.c.role is Role.CANDIDATE
    assert pair.c.counter("unanswered_takeovers") == 1
    steps += [
        Step(5500, TICK),  # serves
        heard(5600, p.Serving(LOWER)),  # no answer behind it: nothing
    ]
    assert run(lib, steps, after=0).c.role is Role.SERVING
    steps += [
        heard(5700, p.Bind(0x20, 41), busy=True),  # an answer it did not send, but it ...
        heard(5800, p.Serving(LOWER), busy=True),  # ... runs a census
    ]
    assert run(lib, steps, after=0).c.role is Role.SERVING
    steps.append(heard(5900, p.Serving(LOWER)))  # backed by the answer: stands by
    assert run(lib, steps, after=0).c.role is Role.STANDBY


def test_an_answer_just_before_its_request_counts(lib: ctypes.CDLL) -> None:
    steps = [
        HELD,
        heard(100, p.Serving(LOWER)),
        heard(1000, p.EtagsFull(42)),
        asked(2000, p.Request(p.PUB_BIND, 3, 42, 2)),  # 1 s after its answer: answered
        asked(2001, p.Knock()),
        heard(2100, p.Census(0)),
        heard(3000, p.Serving(LOWER)),
        heard(4000, p.Serving(LOWER)),
        heard(6000, p.Serving(LOWER)),
    ]
    pair = run(lib, steps, after=0)
    assert pair.c.role is Role.STANDBY
    assert pair.c.counter("unanswered_takeovers") == 0
    steps[2] = heard(999, p.EtagsFull(42))  # 1.001 s before: watched, and never answered
    assert run(lib, steps, after=0).c.counter("unanswered_takeovers") == 1


def test_watched_requests_are_bounded_and_counted(lib: ctypes.CDLL) -> None:
    bound = lib.ups_ecb_host_config(6)
    steps = [HELD, heard(100, p.Serving(LOWER))]
    steps += [asked(200 + i, p.Request(p.SUB_BIND, 3, 1000 + i)) for i in range(bound + 3)]
    pair = run(lib, steps, after=2800)
    assert pair.c.counter("watched_full") == 3
    assert pair.c.counter("unanswered_takeovers") == 1


def test_an_answer_counts_for_a_second_to_the_millisecond(lib: ctypes.CDLL) -> None:
    for gap, watched in ((999, False), (1000, False), (1001, True)):
        steps = [HELD, heard(100, p.Serving(LOWER)), heard(1000, p.Bind(0x20, 42))]
        steps += [Step(1000 + gap, TICK), asked(1000 + gap, p.Request(p.SUB_BIND, 3, 42))]
        steps += [heard(at, p.Serving(LOWER)) for at in (3000, 5000, 7000)]
        pair = run(lib, steps, after=0)
        assert pair.c.counter("unanswered_takeovers") == watched


def test_the_answers_of_the_last_second_are_bounded(lib: ctypes.CDLL) -> None:
    bound = lib.ups_ecb_host_config(6)
    steps = [HELD, heard(100, p.Serving(LOWER))]
    steps += [heard(200 + i, p.Bind(0x20 + i, 1000 + i)) for i in range(bound + 1)]
    for uid, watched in ((1000 + bound, False), (1001, False), (1000, True)):  # 1000 went first
        more = [asked(300, p.Request(p.SUB_BIND, 3, uid))]
        more += [heard(at, p.Serving(LOWER)) for at in (2000, 4000)]
        assert run(lib, steps + more, after=0).c.counter("unanswered_takeovers") == watched


def test_a_wary_one_stands_by_with_an_answer_within_the_backing_time(lib: ctypes.CDLL) -> None:
    wary = [heard(100, p.Serving(LOWER)), asked(1000, p.Knock()), Step(5500, TICK)]  # serves
    for gap, role in ((2000, Role.STANDBY), (2001, Role.SERVING)):
        steps = [*wary, heard(6000, p.Serving(LOWER)), heard(6000 + gap, p.Uses(True, 3, 7))]
        assert run(lib, steps, after=0).c.role is role


@pytest.mark.parametrize(
    ("requests", "answer", "unanswered"),
    [
        ([p.Request(p.SUB_BIND, 3, 42), p.Request(p.PUB_BIND, 4, 42)], p.Bind(0x20, 42), 0),
        ([p.Knock(), p.Knock()], p.Failed(77), 0),  # a join's Failed names a node id
        ([p.Request(p.PUB_BIND, 3, 42, 4)], p.Limit(3, 42), 0),
        ([p.Request(p.PUB_BIND, 3, 42, 4)], p.Failed(41), 1),
        ([p.Knock()], p.EtagsFull(42), 1),
        (
            [p.Request(p.UNSUB, 3, 42), p.Roster(3, 0), p.Request(p.CLAIM, 3, 9)],
            p.Grant(16, 3, 5),
            0,
        ),
    ],
)
def test_what_answers_what(
    lib: ctypes.CDLL, requests: list[p.Management], answer: p.Management, unanswered: int
) -> None:
    binding = any(isinstance(msg, p.Request) for msg in requests)  # (an Assign answers Knocks)
    steps = [HELD, heard(50, p.Assign(4, 8))] if binding else []
    steps += [heard(100, p.Serving(LOWER))]
    steps += [asked(1000 + 100 * i, msg) for i, msg in enumerate(requests)]
    steps += [heard(1900, answer)] + [heard(at, p.Serving(LOWER)) for at in (3000, 5000, 7000)]
    assert run(lib, steps, after=0).c.counter("unanswered_takeovers") == unanswered


def test_the_same_under_asan_with_the_smallest_tables() -> None:
    """The comparison and the bounds, in a child with the ASan runtime, on the asan build
    (UPS_ECB_WATCHED 2: every table fills)."""
    build("asan", targets=VARIANTS, sources=SOURCES)  # built here; loaded by the child only
    code = (
        "from tests.test_cecb_elect import *; lib = load_lib('asan'); "
        "assert lib.ups_ecb_host_config(6) == 2; "
        "comparison(100)(lib); "
        "test_watched_requests_are_bounded_and_counted(lib); "
        "test_the_answers_of_the_last_second_are_bounded(lib)"
    )
    env = {**sanitizer_env(), "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=50)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]


def test_binding_requests_are_watched_only_from_txnodes_heard_assigned(lib: ctypes.CDLL) -> None:
    """A SUB_BIND of a TxNode nobody holds (as far as it knows) is owed no answer: not watched.
    One of a TxNode an Assign of another gave, or claimed within 2 s of a Hello, is, until its
    own next Hello."""
    stand_by = [heard(100, p.Serving(LOWER))]
    servings = [heard(at, p.Serving(LOWER)) for at in (3000, 5000, 7000)]
    unheld = [*stand_by, asked(1000, p.Request(p.SUB_BIND, 5, 42)), *servings]
    assert run(lib, unheld, after=0).c.counter("unanswered_takeovers") == 0
    assigned = [*stand_by, heard(500, p.Assign(5, 9)), *unheld[1:]]
    assert run(lib, assigned, after=0).c.counter("unanswered_takeovers") == 1
    offered = [*stand_by, heard(500, p.Offer(5, 9)), *unheld[1:]]  # an Offer is not held
    assert run(lib, offered, after=0).c.counter("unanswered_takeovers") == 0
    again = [*assigned[:3], Step(3500, TICK), Step(5500, TICK), heard(5600, p.Serving(LOWER))]
    again += [heard(5700, p.Uses(True, 3, 7)), heard(5800, p.Serving(LOWER))]  # stands by
    again += [asked(6000, p.Request(p.SUB_BIND, 5, 43))]  # after its Hello: not held any more
    again += [heard(at, p.Serving(LOWER)) for at in (8000, 10_000, 12_000)]
    pair = run(lib, again, after=0)
    assert pair.c.counter("unanswered_takeovers") == 1
    assert pair.c.role is Role.STANDBY
    for at, watched in ((2200, True), (2201, False)):  # a CLAIM within 2 s of a Hello
        claimed = [*stand_by, heard(200, p.Hello(HIGHER)), asked(at, p.Request(p.CLAIM, 5, 9))]
        claimed += [asked(2300, p.Request(p.SUB_BIND, 5, 42))]
        claimed += [heard(t, p.Serving(LOWER)) for t in (3000, 5000, 7000)]
        assert run(lib, claimed, after=0).c.counter("unanswered_takeovers") == watched
