"""Priority assignment: deadline-monotonic, Audsley's algorithm, the 8-bit field, admission."""

from __future__ import annotations

import itertools
from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ups.rt import (
    MessageSpec,
    NotSchedulable,
    analyze,
    assign_priorities,
    audsley,
    deadline_monotonic,
    to_priority_field,
)

from .conftest import message_sets

F = Fraction

# Deadline-monotonic puts "a" (D = 2.4) above "c" (D = 2.5), but "c" has 0.7 ms of queuing
# jitter and only 1.8 ms left; Audsley's algorithm finds c -> a -> b (125 kbit/s, 11-bit
# identifiers, blocking by an 8-byte frame).
JITTERY = [
    MessageSpec("a", 1, F("2.4"), F("2.4")),
    MessageSpec("b", 8, F("3.2"), F("3.2")),
    MessageSpec("c", 1, F("4.2"), F("2.5"), F("0.7")),
]


def _all_meet(specs: list[MessageSpec], **kwargs: object) -> bool:
    return all(r.schedulable for r in analyze(specs, 125_000, id_bits=11, **kwargs))  # type: ignore[arg-type]


def test_deadline_monotonic_orders_by_deadline_ties_in_input_order() -> None:
    specs = [
        MessageSpec("x", 1, 10, 7),
        MessageSpec("y", 1, 10, 3),
        MessageSpec("z", 1, 10, 7),
        MessageSpec("w", 1, 10, 1, priority=None),
    ]
    ordering = deadline_monotonic(specs)
    assert [s.name for s in ordering] == ["w", "y", "x", "z"]
    assert [s.priority for s in ordering] == [0, 1, 2, 3]


def test_audsley_beats_deadline_monotonic() -> None:
    assert not _all_meet(deadline_monotonic(JITTERY))
    ordering = audsley(JITTERY, 125_000, 11)
    assert [s.name for s in ordering] == ["c", "a", "b"]
    assert [s.priority for s in ordering] == [0, 1, 2]
    assert _all_meet(ordering)


def test_audsley_ignores_given_priorities() -> None:
    given_order = [
        MessageSpec(s.name, s.size_bytes, s.period_ms, s.deadline_ms, s.jitter_ms, rank)
        for rank, s in enumerate(reversed(JITTERY))
    ]
    assert [s.name for s in audsley(given_order, 125_000, 11)] == ["c", "a", "b"]


def test_audsley_names_the_message_that_cannot_fit() -> None:
    specs = [*JITTERY, MessageSpec("d", 8, F(3), F("1.5"))]
    with pytest.raises(NotSchedulable) as caught:
        audsley(specs, 125_000, 11)
    error = caught.value
    assert isinstance(error, ValueError)
    assert error.channel in {"a", "b", "c", "d"}
    assert repr(error.channel) in str(error)
    assert "deadline" in str(error)
    assert error.response_time_ms is None or error.response_time_ms > error.deadline_ms


def test_to_priority_field() -> None:
    ordering = audsley(JITTERY, 125_000, 11)
    assert to_priority_field(ordering) == {"c": 0, "a": 1, "b": 2}
    assert to_priority_field(ordering, first=16, last=18) == {"c": 16, "a": 17, "b": 18}
    # Without priority fields, the sequence order is the priority order.
    assert to_priority_field(JITTERY, first=250) == {"a": 250, "b": 251, "c": 252}
    with pytest.raises(ValueError, match="do not fit"):
        to_priority_field(ordering, first=254)
    with pytest.raises(ValueError, match="first"):
        to_priority_field(ordering, first=10, last=9)
    with pytest.raises(ValueError, match="first"):
        to_priority_field(ordering, last=256)


def test_assign_priorities_admits_or_names_the_missing_channel() -> None:
    assert assign_priorities(JITTERY, 125_000, 11, first=8) == {"c": 8, "a": 9, "b": 10}
    with pytest.raises(NotSchedulable) as caught:
        assign_priorities(JITTERY, 125_000, 11, policy="deadline-monotonic")
    assert caught.value.channel == "c"
    assert "'c'" in str(caught.value)
    with pytest.raises(NotSchedulable) as caught:
        assign_priorities(JITTERY, 125_000, 11, policy="given")
    assert caught.value.channel == "c"  # in the given order a, b, c
    ordering = audsley(JITTERY, 125_000, 11)
    assert assign_priorities(ordering, 125_000, 11, policy="given") == {"c": 0, "a": 1, "b": 2}
    with pytest.raises(ValueError, match="policy"):
        assign_priorities(JITTERY, 125_000, 11, policy="random")  # type: ignore[arg-type]


def test_admission_of_one_channel_too_many() -> None:
    """The admission pattern: declared channels plus a new one; the error names a channel."""
    # 29-bit 8-byte frames take 160 bits = 1.28 ms at 125 kbit/s: blocking + 6 frames = 8.96 ms
    # fit in 10 ms, blocking + 7 frames = 10.24 ms do not.
    channels = [MessageSpec(f"ch{i}", 8, F(10), F(10)) for i in range(6)]
    assert assign_priorities(channels, 125_000) == {f"ch{i}": i for i in range(6)}
    with pytest.raises(NotSchedulable, match="would miss its deadline") as caught:
        assign_priorities([*channels, MessageSpec("new", 8, F(10), F(10))], 125_000)
    assert caught.value.channel.startswith(("ch", "new"))


@settings(max_examples=80, deadline=None)
@given(specs=message_sets(max_size=4), bitrate=st.sampled_from((125_000, 250_000)))
def test_audsley_is_optimal(specs: list[MessageSpec], bitrate: int) -> None:
    """Audsley finds a schedulable ordering exactly when some permutation is schedulable."""
    feasible = any(
        all(r.schedulable for r in analyze(list(order), bitrate, id_bits=11))
        for order in itertools.permutations(specs)
    )
    try:
        ordering = audsley(specs, bitrate, 11)
    except NotSchedulable:
        assert not feasible
    else:
        assert feasible
        assert all(r.schedulable for r in analyze(ordering, bitrate, id_bits=11))
