"""Which CAN-ECB serves a bus: the election between CAN-ECBs, as a pure state machine.

No I/O and no clock. The caller passes the time (seconds on any monotonic clock), hands over
every CAN-ECB frame it hears that it did not send (``heard``), calls ``tick`` when
``deadline`` has come, and sends the frames each call returns. ``CanEcb`` drives it on a
bus; ``tests/test_ecb_election.py`` drives the same code on a simulated one.

The rules (docs/protocol.md, "More than one CAN-ECB"), in short. A CAN-ECB is a *candidate*
from its Hello until its candidacy ends (its recovery window, at most ``MAX_CANDIDACY``), then
it *serves*, and says so with Serving. Claims are ranked by one order that every CAN-ECB
applies alike: a Serving outranks a Hello, and of two of a kind the lower instance wins. So a
candidate stands by on any Serving and on the Hello of a lower instance; a serving CAN-ECB
stands by only on the Serving of a lower instance, and answers every other CAN-ECB frame
(a Hello, a Probe, anything else) with its Serving. A CAN-ECB that stands by sends Probe, which
ranks nowhere: it asks, and a serving CAN-ECB answers, but it never makes anyone stand by or
keeps anyone standing by. Only a Hello or a Serving of another instance keeps a standing-by
CAN-ECB standing by; after ``TAKEOVER`` without one, it says Hello and becomes a candidate.

Why standing by is stable: a serving CAN-ECB answers each Probe within ``SERVING_GAP`` (plus
the bus's delay), and a standing-by one probes every ``PROBE`` s, so it hears a Serving at
least every ``PROBE + SERVING_GAP`` s (< ``TAKEOVER``) for as long as one serves; a candidate
has said Hello and says Serving when its candidacy ends (``MAX_CANDIDACY`` < ``TAKEOVER``).
Why the first to serve stays: a newcomer hears the answer to its Hello while it is a candidate,
unless its candidacy is shorter than that answer's wait (at most ``SERVING_GAP``, and none
when the serving one has answered nothing in the last second).
Why two never stay serving: each sends a Serving at least every ``BEAT`` s, and the higher
instance stands by on hearing the lower one's.
"""

from __future__ import annotations

import enum
import math

from ups._canproto import Hello, Management, Probe, Serving

SERVING_GAP = 1.0  #: at most one Serving in answer per this many seconds (one due sooner waits)
PROBE = 2.0  #: a standing-by CAN-ECB sends Probe this often
TAKEOVER = 4.0  #: ... and takes over after this long without a Hello or Serving of another
BEAT = 10.0  #: a serving CAN-ECB sends Serving at least this often, asked or not
MAX_CANDIDACY = 2.0  #: a candidate serves (and says Serving) at most this long after its Hello

Frame = Hello | Serving | Probe


class Role(enum.Enum):
    STOPPED = "stopped"  #: not started
    CANDIDATE = "candidate"  #: said Hello; stands by on any Serving or a lower Hello
    SERVING = "serving"  #: stands by only on the Serving of a lower instance
    STANDBY = "standby"  #: another CAN-ECB serves; Probe now and then


class Election:
    """The election state of CAN-ECB ``instance``, whose recovery window lasts ``recovery``
    seconds (its candidacy lasts as long, at most ``MAX_CANDIDACY``)."""

    def __init__(self, instance: int, recovery: float = MAX_CANDIDACY) -> None:
        self.instance = instance
        self.candidacy = min(max(recovery, 0.0), MAX_CANDIDACY)
        self.role = Role.STOPPED
        self.reason = ""  #: why it stands by
        self._until = math.inf  # candidate: when the candidacy ends
        self._heard = -math.inf  # standing by: the last Hello or Serving of another
        self._next_probe = math.inf
        self._last_serving = -math.inf  # any Serving (the beat counts from it)
        self._last_answer = -math.inf  # a Serving in answer to another's frame
        self._due: float | None = None  # a Serving owed, to be sent at this time

    @property
    def active(self) -> bool:
        """A candidate or serving: it answers nodes (a candidate as in recovery)."""
        return self.role in (Role.CANDIDATE, Role.SERVING)

    @property
    def deadline(self) -> float | None:
        """When ``tick`` must be called next (None: not before the next frame)."""
        if self.role is Role.CANDIDATE:
            return self._until
        if self.role is Role.SERVING:
            beat = self._last_serving + BEAT
            return beat if self._due is None else min(self._due, beat)
        if self.role is Role.STANDBY:
            return min(self._heard + TAKEOVER, self._next_probe)
        return None

    def start(self, now: float) -> list[Frame]:
        """The CAN-ECB starts: Hello, and a candidacy."""
        return self._candidate(now)

    def heard(self, msg: Management, now: float) -> list[Frame]:
        """A CAN-ECB frame that this one did not send (any kind, also Bind, Assign, ...)."""
        other = msg.instance if isinstance(msg, Hello | Serving | Probe) else None
        if other == self.instance:  # its own instance: an echo or a forger, not a rival
            return []
        if self.role is Role.STANDBY:
            if isinstance(msg, Hello | Serving):
                self._heard = now  # one serves, or is about to
            return []
        if self.role is Role.CANDIDATE:
            if isinstance(msg, Serving):
                return self._stand_by(now, f"CAN-ECB {msg.instance:016x} already serves this bus")
            if isinstance(msg, Hello) and msg.instance < self.instance:
                return self._stand_by(
                    now, f"CAN-ECB {msg.instance:016x} started as well, with a lower instance"
                )
            return []  # a higher Hello stands by on ours; a Probe asks the one that serves
        if self.role is Role.SERVING:
            if isinstance(msg, Serving) and msg.instance < self.instance:
                return self._stand_by(
                    now, f"CAN-ECB {msg.instance:016x} serves this bus too, with a lower instance"
                )
            return self._serve(now)  # whoever sends CAN-ECB frames: this one serves
        return []

    def tick(self, now: float) -> list[Frame]:
        """Timers: the candidacy's end, a Serving owed or due, a Probe, a takeover."""
        if self.role is Role.CANDIDATE and now >= self._until:
            self.role = Role.SERVING
            return self._announce(now)  # standing-by CAN-ECBs hear that one serves
        if self.role is Role.SERVING:
            if self._due is not None and now >= self._due:
                return self._serve(now)
            if now >= self._last_serving + BEAT:
                return self._announce(now)
        elif self.role is Role.STANDBY:
            if now >= self._heard + TAKEOVER:
                self.reason = ""
                return self._candidate(now)
            if now >= self._next_probe:
                self._next_probe = now + PROBE
                return [Probe(self.instance)]
        return []

    def _candidate(self, now: float) -> list[Frame]:
        self.role = Role.CANDIDATE
        self._until = now + self.candidacy
        return [Hello(self.instance)]

    def _stand_by(self, now: float, reason: str) -> list[Frame]:
        self.role = Role.STANDBY
        self.reason = reason
        self._heard = now
        self._next_probe = now + PROBE
        self._due = None
        return []

    def _serve(self, now: float) -> list[Frame]:
        """Serving in answer: now, or (within ``SERVING_GAP`` of the last answer) once the gap
        has passed. The Serving that ends a candidacy and the beat answer nobody: they do not
        count, so that a newcomer's Hello just after them is answered at once."""
        if now >= self._last_answer + SERVING_GAP:  # (as ``deadline`` adds them)
            self._last_answer = now
            self._due = None
            return self._announce(now)
        self._due = self._last_answer + SERVING_GAP
        return []

    def _announce(self, now: float) -> list[Frame]:
        self._last_serving = now
        return [Serving(self.instance)]
