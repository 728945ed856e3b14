"""The Events service's every-change events under a stream of changes faster than their cap:
what must never happen -- two Events closer than the cap allows, a stream whose last change is
never sent, a change neither sent nor counted as coalesced."""

from __future__ import annotations

import asyncio
import itertools

from hypothesis import given, settings
from hypothesis import strategies as st

from ups.jaus._events import EVERY_CHANGE, Events

from .conftest import eventually


@settings(max_examples=10, deadline=None)
@given(
    cap=st.sampled_from([50.0, 200.0, 1000.0]),
    gaps_ms=st.lists(st.sampled_from([0.0, 0.2, 1.0, 3.0]), min_size=5, max_size=120),
)
def test_every_change_events_keep_their_cap_and_end_with_the_latest(
    cap: float, gaps_ms: list[float]
) -> None:
    asyncio.run(_stream(cap, gaps_ms))


async def _stream(cap: float, gaps_ms: list[float]) -> None:
    latest = [0]
    # Each Event with the time it went out on the clock that Events keeps its cap with (the
    # loop's, read once before the answer is asked for): a clock read here, in send, is later
    # than that by however long the answer took, which differs from one Event to the next.
    sent: list[tuple[float, int]] = []
    counters: dict[str, int] = {}
    events = Events(
        report_of=lambda query: "ReportX",
        answer=lambda query: latest[0],
        send=lambda sub, report: sent.append((sub.last_sent, report)),
        cap=lambda report: cap,
        counters=counters,
    )
    events.create("ocu", None, 1, EVERY_CHANGE, 0.0, b"\x00\x00")
    await eventually(lambda: len(sent) == 1)  # the first Event: the answer now
    for value, gap in enumerate(gaps_ms, start=1):
        latest[0] = value
        events.changed("ReportX")
        await asyncio.sleep(gap / 1000)  # the stream's pace, not a wait for a result
    await eventually(lambda: sent[-1][1] == len(gaps_ms))  # the last change always goes out
    for (before, _), (after, _) in itertools.pairwise(sent):
        assert after - before >= 1 / cap - 1e-9  # never faster than the cap
    assert [v for _, v in sent] == sorted(v for _, v in sent)  # in order, never stale
    changes = len(gaps_ms)
    assert counters["events_sent"] == len(sent)
    assert len(sent) - 1 + counters["events_coalesced"] >= changes  # each sent or coalesced
    events.close()
