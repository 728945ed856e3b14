"""The election of libups-ecb (c/ups_ecb_elect.c) on the simulated bus of
tests/test_ecb_election.py: two and three C CAN-ECBs started and stopped at random, frames
delayed, reordered and lost; the same invariants (exactly one active within the bound of
docs/protocol.md, a serving one stands by only on a lower Serving, a newcomer does not
displace the one that serves, ...).

Each CAN-ECB is the C election alone (``ups_ecb_host_elect``, for tests only), on a
millisecond clock that starts just before its wrap: it reads the millisecond that has begun
(the bus's time in seconds, rounded down: its timers never end later than the bus's), and
the C tells when its next timer ends (``ups_ecb__elect_next``), which is when the bus ticks
it. A recovery of 0 s is the C's least, 0.1 s.
"""

from __future__ import annotations

import ctypes
import math

from ups import _canproto as p
from ups.broker._election import Frame, Role

from .test_cecb_elect import HEARD, NEXT, NONE, ROLES, SAY_HELLO, START, TICK, _Config, load_lib
from .test_ecb_election import SETTINGS, _machine

BASE = (1 << 32) - 20_000  #: the C clock at the bus's time 0: it wraps 20 s in
_lib: list[ctypes.CDLL] = []


def _the_lib() -> ctypes.CDLL:
    if not _lib:
        _lib.append(load_lib("full"))
    return _lib[0]


class CCandidate:
    """One C election, as the simulated bus drives an ``Election``."""

    def __init__(self, instance: int, recovery: float) -> None:
        self.lib = lib = _the_lib()
        self.instance = instance
        recovery_ms = max(round(recovery * 1000), 100)
        self.candidacy = min(recovery_ms, 2000) / 1000
        self.ecb = ctypes.create_string_buffer(lib.ups_ecb_host_size())
        cfg = _Config()
        lib.ups_ecb_default_config(ctypes.byref(cfg))
        cfg.recovery_ms = recovery_ms
        assert lib.ups_ecb_init(self.ecb, ctypes.byref(cfg), instance) == 0
        self.ms = 0  #: the bus's time of the last call, ms

    def _call(self, now: float, what: int, msg: p.Management | None = None) -> list[Frame]:
        self.ms = math.floor(now * 1000 + 1e-9)  # the ms begun (a hair over: float error)
        can_id, data = p.encode(msg) if msg is not None else (0, b"")
        clock = (BASE + self.ms) & 0xFFFF_FFFF
        verdict = self.lib.ups_ecb_host_elect(self.ecb, clock, what, can_id, data, len(data), 0)
        frames: list[Frame] = [p.Hello(self.instance)] if verdict & SAY_HELLO else []
        while frame := self.lib.ups_ecb_tx_peek(self.ecb):
            f = frame.contents
            sent = p.decode(f.id, bytes(f.data[: f.len]))
            assert isinstance(sent, p.Serving | p.Probe), sent
            frames.append(sent)
            self.lib.ups_ecb_tx_pop(self.ecb)
        return frames

    @property
    def role(self) -> Role:
        return ROLES[self.lib.ups_ecb_role(self.ecb)]

    @property
    def active(self) -> bool:
        return self.role in (Role.CANDIDATE, Role.SERVING)

    @property
    def deadline(self) -> float | None:
        clock = (BASE + self.ms) & 0xFFFF_FFFF
        left = self.lib.ups_ecb_host_elect(self.ecb, clock, NEXT, 0, b"", 0, 0)
        return None if left == NONE else (self.ms + left) / 1000

    def start(self, now: float) -> list[Frame]:
        self._call(now, START)
        return [p.Hello(self.instance)]  # the dispatcher says it

    def heard(self, msg: p.Management, now: float) -> list[Frame]:
        return self._call(now, HEARD, msg)

    def tick(self, now: float) -> list[Frame]:
        return self._call(now, TICK)


TestTwoCCanEcbs = _machine(CCandidate, 2).TestCase
TestTwoCCanEcbs.settings = SETTINGS
TestThreeCCanEcbs = _machine(CCandidate, 3).TestCase
TestThreeCCanEcbs.settings = SETTINGS


def test_the_c_candidate_is_driven_as_the_python_one() -> None:
    """A lone one: Hello, then Serving when its candidacy ends, and the beat."""
    ecb = CCandidate(5, 0.2)
    roles = []
    assert ecb.start(1.0) == [p.Hello(5)]
    roles.append(ecb.role)
    assert ecb.deadline == 1.2
    assert ecb.tick(1.2) == [p.Serving(5)]
    roles.append(ecb.role)
    assert ecb.deadline == 11.2
    assert ecb.heard(p.Probe(7), 3.0) == [p.Serving(5)]
    assert ecb.heard(p.Serving(4), 3.5) == []
    roles.append(ecb.role)
    assert ecb.deadline == 5.5  # its Probe
    assert roles == [Role.CANDIDATE, Role.SERVING, Role.STANDBY]
