"""What the bridge takes from ROS, before it decodes anything: a rate bound per topic, and each
ROS publisher's sequence numbers followed with its gaps bounded before they count as loss.

Anyone on the ROS 2 router may put on a topic's key, at any rate, with any attachment; what
the bridge takes goes onto the UPS side (on CAN, frames on the bus). So, per topic:

- **Rate**: a token bucket of ``burst`` samples refilled at ``max_rate`` samples a second
  (the map's; 100/s and 20 by default). A sample that finds it empty is dropped and counted
  (``rate_limited``): after a silence ``burst`` samples go through back to back, and over any
  time ``t`` at most ``burst + max_rate * t`` do.
- **Loss**: the attachment's sequence number is the sender's word. A gap in one publisher's
  numbers counts as loss (``ros_lost``) only within the topic's *loss credit*: the samples its
  ``max_rate`` would have carried since the bridge started, at most ``LOSS_WINDOW`` seconds'
  worth, each counted gap spending its share. A number that goes back, or jumps further than
  that, is a restart or a forgery: counted once (``ros_jumps``), not as loss, and followed from
  there. So ``ros_lost`` grows by at most ``max_rate`` a second per topic (after a first
  ``LOSS_WINDOW`` seconds' worth), whatever numbers are forged.

Every sample is followed, those the rate bound then drops too (they are no gap). Called from
Zenoh's threads: the caller holds one lock around ``admit``.
"""

from __future__ import annotations

from dataclasses import dataclass

from ._rmw import read_attachment

DEFAULT_RATE = 100.0  #: samples a second a topic takes from ROS unless its map says otherwise
DEFAULT_BURST = 20  #: samples it takes back to back after a silence
MAX_RATE = 10_000.0  #: the most a map may give (a 1 Mbit/s CAN bus carries ~8,000 frames/s)
MAX_BURST = 10_000
LOSS_WINDOW = 60.0  #: seconds of samples at max_rate a topic's loss credit holds at most
MAX_SOURCES = 4096  #: ROS publishers whose sequence numbers are followed (the oldest goes)


@dataclass(slots=True)
class Gate:
    """One topic's rate bucket and loss credit (``now`` is ``time.monotonic()``)."""

    max_rate: float
    burst: int
    tokens: float
    credit: float
    last: float

    @classmethod
    def new(cls, max_rate: float, burst: int, now: float) -> Gate:
        return cls(max_rate, burst, float(burst), 0.0, now)

    def refill(self, now: float) -> None:
        elapsed = max(0.0, now - self.last)
        self.last = now
        self.tokens = min(float(self.burst), self.tokens + elapsed * self.max_rate)
        self.credit = min(self.max_rate * LOSS_WINDOW, self.credit + elapsed * self.max_rate)

    def take(self) -> bool:
        """One sample through, if the bucket holds one."""
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class Admission:
    """The gates of the bridge's topics and the sequence numbers of ROS publishers; it counts
    into ``counters`` (``no_attachment``, ``ros_lost``, ``ros_jumps``, ``rate_limited``)."""

    def __init__(self, counters: dict[str, int]) -> None:
        self.counters = counters
        self._expected: dict[bytes, int] = {}  # a ROS publisher's GID -> its next number

    def admit(self, gate: Gate, extra: bytes | None, now: float) -> bool:
        """Follow the sample's attachment ``extra``; whether the topic's rate lets it in."""
        gate.refill(now)
        found = read_attachment(extra)
        if found is None:
            self.counters["no_attachment"] += 1
        else:
            self._follow(gate, found.gid, found.sequence)
        if gate.take():
            return True
        self.counters["rate_limited"] += 1
        return False

    def _follow(self, gate: Gate, who: bytes, sequence: int) -> None:
        expected = self._expected.get(who)
        if expected is None:
            if len(self._expected) >= MAX_SOURCES:
                del self._expected[next(iter(self._expected))]
        elif sequence != expected:
            gap = sequence - expected
            if 0 < gap <= gate.credit:
                gate.credit -= gap
                self.counters["ros_lost"] += gap
            else:  # back, or further than the topic could have carried: restart or forgery
                self.counters["ros_jumps"] += 1
        self._expected[who] = sequence + 1
