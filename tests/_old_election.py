"""The election rules of ``broker/can_ecb.py`` before issue 29 (commit 004d99a), transcribed
into the interface of ``broker._election.Election``, so that ``tests/test_ecb_election.py``
can show that its state machine finds their flaw: two CAN-ECBs that both stand by for good.

The old rules: a CAN-ECB in recovery that hears Serving of another stands by ("it was first");
one that hears a Hello or Serving of a lower instance in recovery, or a Serving of a lower
instance at any time, stands by; otherwise it answers Serving (at most one a second, the
others dropped). A standing-by CAN-ECB sends Serving every 2 s as its probe and takes over
when it has heard no Hello or Serving of another instance for 4 s (checked at each probe).
"""

from __future__ import annotations

import math

from ups._canproto import Hello, Management, Serving
from ups.broker._election import Frame, Role

SERVING_GAP = 1.0
STANDBY_PROBE = 2.0


class OldElection:
    def __init__(self, instance: int, recovery: float = 2.0) -> None:
        self.instance = instance
        self.recovery = recovery
        self.candidacy = recovery
        self.reason = ""
        self.started = False
        self.standby = False
        self.recovering = False
        self._recovered_at = math.inf
        self._last_serving = -1.0e9
        self._other_heard = 0.0
        self._probe_at = math.inf

    @property
    def role(self) -> Role:
        if not self.started:
            return Role.STOPPED
        if self.standby:
            return Role.STANDBY
        return Role.CANDIDATE if self.recovering else Role.SERVING

    @property
    def active(self) -> bool:
        return self.role in (Role.CANDIDATE, Role.SERVING)

    @property
    def deadline(self) -> float | None:
        due = min(self._recovered_at, self._probe_at)
        return None if due == math.inf else due

    def start(self, now: float) -> list[Frame]:
        self.started = True
        return self._hello(now)

    def _hello(self, now: float) -> list[Frame]:
        self.recovering = True
        self._recovered_at = now + self.recovery
        return [Hello(self.instance)]

    def heard(self, msg: Management, now: float) -> list[Frame]:
        if self.standby:
            if isinstance(msg, Hello | Serving) and msg.instance != self.instance:
                self._other_heard = now
            return []
        if isinstance(msg, Hello | Serving):
            if msg.instance == self.instance:
                return []
            first = isinstance(msg, Serving) and self.recovering
            if first or (
                (self.recovering or isinstance(msg, Serving)) and msg.instance < self.instance
            ):
                self.standby = True
                self.reason = f"CAN-ECB {msg.instance:016x} already serves this bus"
                self._other_heard = now
                self._probe_at = now + STANDBY_PROBE
                return []
        return self._serving(now)

    def _serving(self, now: float) -> list[Frame]:
        if now - self._last_serving >= SERVING_GAP:
            self._last_serving = now
            return [Serving(self.instance)]
        return []

    def tick(self, now: float) -> list[Frame]:
        frames: list[Frame] = []
        if now >= self._recovered_at:
            self._recovered_at = math.inf
            self.recovering = False
        if now >= self._probe_at:
            self._probe_at = math.inf
            if not self.standby:
                return frames
            if now - self._other_heard > 2 * STANDBY_PROBE:
                self.standby = False
                return self._hello(now)
            self._probe_at = now + STANDBY_PROBE
            frames.append(Serving(self.instance))
        return frames
