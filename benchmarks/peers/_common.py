"""Helpers shared by the peer modules."""

from __future__ import annotations

import time
from collections.abc import Callable

from ups.benchmarks.peers import PROBE, START_TIMEOUT, SinkResult


def probe_until_echoed(
    send: Callable[[bytes], None],
    wait_echo: Callable[[float], bytes | None],
    timeout: float = 10.0,
    interval: float = 0.02,
) -> None:
    """Send :data:`PROBE` every ``interval`` s until one comes back (both ways subscribed).

    ``wait_echo(t)`` returns the next message received within ``t`` seconds, or None.
    Raises TimeoutError after ``timeout`` seconds. Later echoes of surplus probes are left
    for the pinger to ignore.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        send(PROBE)
        if wait_echo(interval) == PROBE:
            return
    raise TimeoutError(f"no echo of a probe within {timeout} s")


class Counter:
    """Counts a sink's arrivals; knows when the sink is done or should give up.

    The sink gives up when nothing arrived for ``idle_timeout`` seconds since the last
    message, or for :data:`START_TIMEOUT` seconds since the counter was made.
    """

    def __init__(self, count: int, idle_timeout: float) -> None:
        self.count = count
        self.idle_timeout = idle_timeout
        self.received = 0
        self.started = time.perf_counter()
        self.first = 0.0
        self.last = 0.0

    def add(self, n: int = 1) -> None:
        """Record ``n`` messages arriving now."""
        now = time.perf_counter()
        if self.received == 0:
            self.first = now
        self.received += n
        self.last = now

    @property
    def done(self) -> bool:
        """True once ``count`` messages have arrived."""
        return self.received >= self.count

    def remaining(self) -> float:
        """Seconds left before the sink gives up (0.0 when it should give up now)."""
        if self.received == 0:
            deadline = self.started + START_TIMEOUT
        else:
            deadline = self.last + self.idle_timeout
        return max(0.0, deadline - time.perf_counter())

    def finished(self) -> bool:
        """True when the sink should stop: all arrived, or it waited long enough."""
        return self.done or self.remaining() == 0.0

    def result(self) -> SinkResult:
        """The counts so far, as a :class:`SinkResult`."""
        return SinkResult(self.received, self.last - self.first)
