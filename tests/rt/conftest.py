"""Shared fixtures and Hypothesis strategies for the real-time analysis tests."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

from hypothesis import strategies as st

from ups.rt import MessageSpec

HERE = Path(__file__).parent
SAE_CSV = HERE / "data" / "sae_benchmark_messages.csv"
"""A copy of shared/data/sae_benchmark_messages.csv, so the tests run without shared/."""
SHARED_SAE_CSV = HERE.parents[2] / "shared" / "data" / "sae_benchmark_messages.csv"


def _tenths(low: int, high: int) -> st.SearchStrategy[Fraction]:
    return st.integers(low, high).map(lambda n: Fraction(n, 10))


@st.composite
def message_sets(
    draw: st.DrawFn,
    min_size: int = 1,
    max_size: int = 6,
    min_period_tenths: int = 10,
    max_period_tenths: int = 200,
) -> list[MessageSpec]:
    """Random message sets: periods 1..20 ms, jitter below the period, deadlines up to 2 T."""
    count = draw(st.integers(min_size, max_size))
    specs = []
    for index in range(count):
        period = draw(_tenths(min_period_tenths, max_period_tenths))
        jitter = draw(st.integers(0, int(period * 10) - 1).map(lambda n: Fraction(n, 10)))
        deadline = draw(_tenths(1, int(period * 20)))
        size = draw(st.integers(0, 8))
        specs.append(MessageSpec(f"m{index}", size, period, deadline, jitter))
    return specs
