"""Discrete-event simulation of CAN arbitration, bit-accurate, for checking the analysis.

Time is kept in integer ticks (a common denominator of the bit time and every given time), so
the simulation is exact. Whenever the bus is idle and frames are pending, the pending frame of
highest priority wins arbitration (a frame queued exactly when the bus goes idle takes part) and
is sent without preemption; its length includes the 3-bit interframe space, so the next
arbitration starts when it ends. Instances of the same message go out in order.
"""

from __future__ import annotations

import heapq
import math
import random
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Literal

from ._frames import _actual_frame_bits, frame_bits
from ._model import MessageSpec, _exact, _ordered

Jitter = Literal["random", "worst"]
SimStuffing = Literal["actual", "worst", "none"]


@dataclass(frozen=True)
class Observation:
    """What the simulation saw for one message.

    ``worst_response_ms`` is the longest time from an instance's nominal release to the end of
    its frame (``None`` if no instance was released), ``instances`` how many were sent and
    ``deadline_misses`` how many of them ended after their deadline.
    """

    name: str
    worst_response_ms: Fraction | None
    instances: int
    deadline_misses: int


@dataclass(frozen=True)
class _Release:
    actual: int
    nominal: int
    rank: int
    instance: int


def simulate(
    specs: Sequence[MessageSpec],
    bitrate: int,
    duration_ms: Fraction | float,
    *,
    id_bits: int = 29,
    jitter: Jitter = "random",
    stuffing: SimStuffing = "actual",
    seed: int = 0,
    fd: bool = False,
) -> list[Observation]:
    """Replay ``specs`` on a simulated bus and report observed response times, in input order.

    Every instance whose nominal release falls before ``duration_ms`` is released and sent
    (the bus runs on until all of them are out, so the work is bounded by the horizon).

    ``jitter="random"``: instance ``n`` has nominal release ``n * T`` and is queued a uniformly
    random time in ``[0, J]`` later (drawn on the tick grid). ``jitter="worst"``: the synchronous
    critical instant; every message's first instance is queued at time 0 after its full jitter
    (nominal release ``-J``), and later ones at ``n * T - J`` with no jitter, so higher-priority
    traffic arrives as densely as its jitter allows. No pattern is the worst case for every
    message at once (a blocking lower-priority frame, for one, cannot precede them all).

    ``stuffing="actual"`` sends each instance with random payload bytes and counts the stuff bits
    of the real bit sequence (identifiers follow the priority ranks: rank ``r`` is identifier
    ``r`` with 11 bits and ``r << 21`` with 29, the UPS priority field); ``"worst"`` and
    ``"none"`` use ``frame_bits``. ``fd=True`` needs ``"worst"`` or ``"none"``.
    """
    if isinstance(bitrate, bool) or not isinstance(bitrate, int) or bitrate <= 0:
        raise ValueError(f"bitrate must be a positive integer (bit/s), not {bitrate!r}")
    if jitter not in ("random", "worst"):
        raise ValueError(f"jitter must be 'random' or 'worst', not {jitter!r}")
    if stuffing not in ("actual", "worst", "none"):
        raise ValueError(f"stuffing must be 'actual', 'worst' or 'none', not {stuffing!r}")
    if fd and stuffing == "actual":
        raise ValueError("the simulation counts actual stuff bits for classic CAN only")
    horizon = _exact(duration_ms)
    if horizon <= 0:
        raise ValueError(f"duration_ms must be positive, not {duration_ms}")
    order = _ordered(specs)
    if any(spec.frames != 1 for spec in order):
        raise ValueError("the simulation sends one frame per instance (frames=1)")
    if id_bits == 11 and len(order) > 2048:
        raise ValueError("more messages than 11-bit identifiers")
    tau = Fraction(1000, bitrate)
    scale = math.lcm(
        tau.denominator,
        horizon.denominator,
        *(
            value.denominator
            for spec in order
            for value in (spec.period_ms, spec.jitter_ms, spec.deadline_ms)
        ),
    )

    def ticks(value: Fraction) -> int:
        product = value * scale
        assert product.denominator == 1
        return product.numerator

    bit = ticks(tau)
    end = ticks(horizon)
    rng = random.Random(seed)
    fixed = [
        frame_bits(spec.size_bytes, id_bits, stuffing, fd) if stuffing != "actual" else 0
        for spec in order
    ]
    if stuffing == "actual":
        # Validates the sizes up front rather than at the first instance.
        for spec in order:
            frame_bits(spec.size_bytes, id_bits, "none")
    identifiers = [
        rank if id_bits == 11 or len(order) > 256 else rank << 21 for rank in range(len(order))
    ]

    releases: list[_Release] = []
    for rank, spec in enumerate(order):
        period, jit = ticks(spec.period_ms), ticks(spec.jitter_ms)
        if jitter == "worst":
            count = -(-(end + jit) // period)
            for n in range(count):
                nominal = n * period - jit
                releases.append(_Release(0 if n == 0 else nominal, nominal, rank, n))
        else:
            count = -(-end // period)
            for n in range(count):
                nominal = n * period
                releases.append(_Release(nominal + rng.randint(0, jit), nominal, rank, n))
    releases.sort(key=lambda release: (release.actual, release.rank, release.instance))

    worst: list[int | None] = [None] * len(order)
    sent = [0] * len(order)
    misses = [0] * len(order)
    deadlines = [ticks(spec.deadline_ms) for spec in order]
    pending: list[tuple[int, int, int]] = []  # (rank, instance, nominal)
    now = 0
    next_release = 0
    while next_release < len(releases) or pending:
        if not pending:
            now = max(now, releases[next_release].actual)
        while next_release < len(releases) and releases[next_release].actual <= now:
            release = releases[next_release]
            heapq.heappush(pending, (release.rank, release.instance, release.nominal))
            next_release += 1
        rank, _, nominal = heapq.heappop(pending)
        if stuffing == "actual":
            payload = rng.randbytes(order[rank].size_bytes)
            length = _actual_frame_bits(identifiers[rank], payload, id_bits)
        else:
            length = fixed[rank]
        now += length * bit
        response = now - nominal
        previous = worst[rank]
        worst[rank] = response if previous is None else max(previous, response)
        sent[rank] += 1
        if response > deadlines[rank]:
            misses[rank] += 1

    observed: dict[str, Observation] = {}
    for rank, spec in enumerate(order):
        value = worst[rank]
        observed[spec.name] = Observation(
            name=spec.name,
            worst_response_ms=None if value is None else Fraction(value, scale),
            instances=sent[rank],
            deadline_misses=misses[rank],
        )
    return [observed[spec.name] for spec in specs]
