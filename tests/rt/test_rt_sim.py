"""The CAN arbitration simulation, checked by hand and against the analysis."""

from __future__ import annotations

from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ups.rt import MessageSpec, analyze, load_csv, simulate

from .conftest import SAE_CSV, message_sets

F = Fraction


def test_hand_checked_trace() -> None:
    """1 Mbit/s, 11-bit identifiers, worst-case frames: hi 65 bits, lo 135 bits.

    Synchronous start: hi [0, 0.065], lo [0.065, 0.2]; lo's first instance was nominally
    released 0.5 ms earlier (all of its jitter), so it responds in 0.7 ms. Later instances of lo
    arrive at 1.5 and 3.5 ms on an idle bus: 0.135 ms.
    """
    hi = MessageSpec("hi", 1, period_ms=1, deadline_ms=1)
    lo = MessageSpec("lo", 8, period_ms=2, deadline_ms=F("0.6"), jitter_ms=F("0.5"))
    observed = simulate([hi, lo], 1_000_000, 4, id_bits=11, jitter="worst", stuffing="worst")
    assert [o.name for o in observed] == ["hi", "lo"]
    assert observed[0].worst_response_ms == F("0.065")
    assert observed[1].worst_response_ms == F("0.7")
    assert [o.instances for o in observed] == [4, 3]  # nominal releases before 4 ms
    assert [o.deadline_misses for o in observed] == [0, 1]
    (bound_hi, bound_lo) = analyze([hi, lo], 1_000_000, id_bits=11, blocking="lower-priority")
    assert bound_lo.response_time_ms == F("0.7")  # the analysis is tight here
    assert bound_hi.response_time_ms == F("0.065") + F("0.135")  # blocking the sim did not show


def test_no_stuffing_and_priority_fields() -> None:
    # Without stuffing an 8-byte 11-bit frame is 111 bits; "b" has the higher priority value 0.
    a = MessageSpec("a", 8, period_ms=10, deadline_ms=10, priority=1)
    b = MessageSpec("b", 8, period_ms=10, deadline_ms=10, priority=0)
    observed = simulate([a, b], 1_000_000, 10, id_bits=11, jitter="worst", stuffing="none")
    assert [o.worst_response_ms for o in observed] == [F("0.222"), F("0.111")]


def test_random_jitter_is_reproducible_and_bounded() -> None:
    specs = load_csv(SAE_CSV)
    first = simulate(specs, 500_000, 200, id_bits=11, seed=7)
    assert first == simulate(specs, 500_000, 200, id_bits=11, seed=7)
    assert first != simulate(specs, 500_000, 200, id_bits=11, seed=8)
    for spec, seen in zip(specs, first, strict=True):
        assert seen.name == spec.name
        assert seen.instances == -(-200 // spec.period_ms)
        assert seen.worst_response_ms is not None and seen.worst_response_ms > 0


@pytest.mark.parametrize("bitrate", [250_000, 500_000, 1_000_000])
@pytest.mark.parametrize("jitter", ["worst", "random"])
def test_sae_observed_within_davis2007(bitrate: int, jitter: str) -> None:
    specs = load_csv(SAE_CSV)
    bounds = analyze(specs, bitrate, id_bits=11, blocking="lower-priority")
    seen = simulate(specs, bitrate, 1000, id_bits=11, jitter=jitter, stuffing="worst")  # type: ignore[arg-type]
    for bound, observation in zip(bounds, seen, strict=True):
        assert bound.response_time_ms is not None
        assert observation.worst_response_ms is not None
        assert observation.worst_response_ms <= bound.response_time_ms


@settings(max_examples=300, deadline=None)
@given(
    specs=message_sets(max_size=6),
    bitrate=st.sampled_from((125_000, 250_000, 500_000, 1_000_000)),
    id_bits=st.sampled_from((11, 29)),
    jitter=st.sampled_from(("worst", "random")),
    stuffing=st.sampled_from(("actual", "worst")),
    seed=st.integers(0, 2**16),
)
def test_observed_never_above_davis2007_bound(
    specs: list[MessageSpec], bitrate: int, id_bits: int, jitter: str, stuffing: str, seed: int
) -> None:
    bounds = analyze(specs, bitrate, "davis2007", id_bits, blocking="lower-priority")
    horizon = min(F(60), 4 * max(spec.period_ms for spec in specs))
    seen = simulate(
        specs,
        bitrate,
        horizon,
        id_bits=id_bits,
        jitter=jitter,  # type: ignore[arg-type]
        stuffing=stuffing,  # type: ignore[arg-type]
        seed=seed,
    )
    for bound, observation in zip(bounds, seen, strict=True):
        assert observation.worst_response_ms is not None
        if bound.response_time_ms is not None:
            assert observation.worst_response_ms <= bound.response_time_ms
            if bound.schedulable:
                assert observation.deadline_misses == 0


def test_tindell1994_promises_a_deadline_that_is_missed() -> None:
    """Davis et al. 2007's counter-example shape: the lowest message's second instance misses.

    125 kbit/s, 11-bit identifiers, 8-byte frames. tindell1994 (with Tindell's blocking by
    lower-priority frames only) checks C's first instance: 3 frames, 3.12 ms <= 3.6 ms. On the
    bus, C's first instance ends at 3.24 ms, after A's second release (2.6 ms), which goes
    next; B's second instance (4.0 ms) and A's third (5.2 ms) then beat C's second instance
    (3.6 ms), which ends at 7.56 ms: 3.96 ms after its release. davis2007 bounds exactly that.
    """
    specs = [
        MessageSpec("A", 8, F("2.6"), F("2.6")),
        MessageSpec("B", 8, F(4), F(4)),
        MessageSpec("C", 8, F("3.6"), F("3.6")),
    ]
    tindell = analyze(specs, 125_000, "tindell1994", 11, blocking="lower-priority")
    assert all(result.schedulable for result in tindell)
    seen = simulate(specs, 125_000, 40, id_bits=11, jitter="worst", stuffing="worst")
    assert seen[2].worst_response_ms == F("3.96")
    assert seen[2].deadline_misses >= 1
    # Not a matter of frame lengths: C's first instance on the bus (3 x 1.08 ms) meets 3.6 ms.
    assert 3 * F("1.08") <= specs[2].deadline_ms
    davis = analyze(specs, 125_000, "davis2007", 11, blocking="lower-priority")
    assert davis[2].response_time_ms == F("3.96") and not davis[2].schedulable


def test_table_1_method_ignores_queuing_jitter() -> None:
    """Table 1's computation leaves J out: a message queued up to 2.5 ms late still 'meets' 3 ms.

    tindell1994: 130-bit blocking + 130-bit frame at 8 us = 2.08 ms. On the bus the frame is
    queued 2.5 ms after its nominal release and takes 1.08 ms (135 bits): 3.58 ms.
    """
    spec = MessageSpec("late", 8, period_ms=10, deadline_ms=3, jitter_ms=F("2.5"))
    (promise,) = analyze([spec], 125_000, "tindell1994", 11)
    assert promise.response_time_ms == F("2.08") and promise.schedulable
    (seen,) = simulate([spec], 125_000, 50, id_bits=11, jitter="worst", stuffing="worst")
    assert seen.worst_response_ms == F("3.58") and seen.deadline_misses == 1
    (bound,) = analyze([spec], 125_000, "davis2007", 11)
    assert bound.response_time_ms == F("2.5") + 2 * F("1.08") and not bound.schedulable


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"bitrate": -1}, "bitrate"),
        ({"duration_ms": 0}, "duration"),
        ({"jitter": "some"}, "jitter"),
        ({"stuffing": "best"}, "stuffing"),
        ({"fd": True}, "classic"),
    ],
)
def test_invalid_parameters(kwargs: dict[str, object], match: str) -> None:
    arguments: dict[str, object] = {
        "specs": [MessageSpec("a", 1, 1, 1)],
        "bitrate": 500_000,
        "duration_ms": 10,
    }
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        simulate(**arguments)  # type: ignore[arg-type]


def test_fd_with_worst_case_frames() -> None:
    spec = MessageSpec("big", 64, period_ms=1, deadline_ms=1)
    (seen,) = simulate([spec], 1_000_000, 5, fd=True, stuffing="worst", jitter="worst")
    assert seen.worst_response_ms == F(736, 1000)  # 736 bits, 29-bit identifier
