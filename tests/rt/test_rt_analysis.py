"""Response-time analysis: paper 000's Table 1, hand-checked cases, and davis2007 >= tindell1994."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ups.rt import MessageSpec, analyze, frame_bits, load_csv

from .conftest import SAE_CSV, SHARED_SAE_CSV, message_sets

F = Fraction

# Table 1 of paper 000 (Tindell & Burns 1994 on the SAE benchmark): the first eighteen rows,
# the ones the paper prints, R in ms at 125, 250, 500 and 1000 kbit/s; a trailing "x" marks a
# missed deadline. Section 4.2: no queuing jitter; blocking by one 8-byte frame (130 bits);
# C_m from equation (1) with the quotient rounded down (63 bits for one byte); tau_bit = 1/bitrate.
# Where no higher-priority message is queued twice (every cell at 250 kbit/s and above), each row
# adds one C_m to the row above, as the paper says; at 125 kbit/s the 5 ms messages recur from
# row 9 on and the set overloads the bus.
TABLE_1 = """
14 1.544  0.772 0.386 0.193
9  2.048  1.024 0.512 0.256
49 2.552  1.276 0.638 0.319
42 3.056  1.528 0.764 0.382
8  3.560  1.780 0.890 0.445
7  4.064  2.032 1.016 0.508
43 4.568  2.284 1.142 0.571
11 5.072x 2.536 1.268 0.634
32 9.104x 2.788 1.394 0.697
29 10.112x 3.040 1.520 0.760
30 15.152x 3.292 1.646 0.823
53 20.192x 3.544 1.772 0.886
48 29.768x 3.796 1.898 0.949
46 30.272x 4.048 2.024 1.012
44 39.848x 4.300 2.150 1.075
40 40.352x 4.552 2.276 1.138
39 49.928x 4.804 2.402 1.201
27 50.432x 5.056 2.528 1.264
"""
BITRATES = (125_000, 250_000, 500_000, 1_000_000)


def _table_1() -> list[tuple[str, list[tuple[Fraction, bool]]]]:
    rows = []
    for line in TABLE_1.strip().splitlines():
        name, *cells = line.split()
        rows.append((name, [(F(cell.rstrip("x")), not cell.endswith("x")) for cell in cells]))
    return rows


def test_sae_copy_matches_shared_data() -> None:
    if not SHARED_SAE_CSV.exists():
        pytest.skip("shared/ is not beside the repository")
    assert SAE_CSV.read_bytes() == SHARED_SAE_CSV.read_bytes()


def test_load_sae_benchmark() -> None:
    specs = load_csv(SAE_CSV)
    assert len(specs) == 53
    assert specs[0] == MessageSpec("14", 1, F(50), F(5), F(1, 10))
    assert [spec.name for spec in specs[:3]] == ["14", "9", "49"]
    assert all(spec.priority is None for spec in specs)


def test_worked_example_of_section_4_2() -> None:
    """Highest priority message at 250 kbit/s: 130 bits blocking + 63 bits at 4 us = 0.772 ms."""
    result = analyze(load_csv(SAE_CSV), 250_000, "tindell1994", id_bits=11)[0]
    assert result.name == "14"
    assert result.response_time_ms == F("0.772")
    assert result.schedulable


@pytest.mark.parametrize("column", range(4), ids=[f"{b // 1000}kbit" for b in BITRATES])
def test_tindell1994_reproduces_table_1(column: int) -> None:
    results = analyze(load_csv(SAE_CSV), BITRATES[column], "tindell1994", id_bits=11)
    for (name, cells), result in zip(_table_1(), results, strict=False):
        expected, meets = cells[column]
        assert result.name == name
        assert result.response_time_ms == expected, name
        assert result.schedulable is meets, name


def test_table_1_rows_add_one_frame_each_where_nothing_recurs() -> None:
    """Section 4.2: each row is the row above plus C_m (while no message is queued twice)."""
    for bitrate in BITRATES[1:]:
        tau = F(1000, bitrate)
        results = analyze(load_csv(SAE_CSV), bitrate, "tindell1994", id_bits=11)[:18]
        for row, result in enumerate(results, start=1):
            assert result.response_time_ms == (130 + 63 * row) * tau


def test_tindell1994_leaves_out_queuing_jitter() -> None:
    specs = load_csv(SAE_CSV)
    without = [MessageSpec(s.name, s.size_bytes, s.period_ms, s.deadline_ms) for s in specs]
    for bitrate in BITRATES:
        assert analyze(specs, bitrate, "tindell1994", 11) == analyze(
            without, bitrate, "tindell1994", 11
        )
        assert analyze(specs, bitrate, "davis2007", 11) != analyze(
            without, bitrate, "davis2007", 11
        )


def test_single_message_by_hand() -> None:
    # 29-bit identifiers, 4 bytes: 54 + 32 + 13 + floor(85 / 4) = 120 bits; blocking by the
    # longest 29-bit frame, 160 bits; at 500 kbit/s a bit takes 2 us.
    spec = MessageSpec("a", 4, period_ms=10, deadline_ms=1, jitter_ms=F("0.25"))
    (result,) = analyze([spec], 500_000)
    assert result.response_time_ms == F("0.25") + (160 + 120) * F(2, 1000)
    assert result.schedulable
    (textbook,) = analyze([spec], 500_000, blocking="lower-priority")
    assert textbook.response_time_ms == F("0.25") + 120 * F(2, 1000)


def test_two_messages_by_hand() -> None:
    # 11-bit identifiers at 1 Mbit/s: 8 bytes = 135 bits = 0.135 ms, 2 bytes = 34 + 16 + 13 +
    # floor(49 / 4) = 75 bits. "hi" every 0.2 ms (jitter 0.05), "lo" every 1 ms.
    hi = MessageSpec("hi", 8, period_ms=F("0.2"), deadline_ms=F("0.2"), jitter_ms=F("0.05"))
    lo = MessageSpec("lo", 2, period_ms=1, deadline_ms=1)
    c_hi, c_lo = F("0.135"), F("0.075")
    r_hi, r_lo = analyze([hi, lo], 1_000_000, id_bits=11, blocking="lower-priority")
    assert r_hi.response_time_ms == F("0.05") + c_lo + c_hi  # blocked once by "lo"
    # "lo": busy period t = ceil((t + 0.05) / 0.2) 0.135 + ceil(t / 1) 0.075 -> 0.345 (2 x hi),
    # so one instance; w = ceil((w + 0.05 + 0.001) / 0.2) * 0.135 stays at 0.135 (0.186 < 0.2).
    assert r_lo.response_time_ms == c_hi + c_lo
    assert r_lo.schedulable
    assert frame_bits(8, 11) == 135 and frame_bits(2, 11) == 75


def test_later_instance_in_busy_period_is_the_worst() -> None:
    """The push-through example (Davis et al. 2007, sec. 3): C's second instance responds later.

    8-byte frames with 11-bit identifiers at 125 kbit/s take 135 bits = 1.08 ms. For C, with A
    and B above it and no blocking: instance 0 waits w(0) = 2.16 (A, B once), R(0) = 3.24;
    instance 1 waits w(1) = 1.08 + ... -> 6.48 (A three times, B twice), R(1) = 6.48 - 3.6 + 1.08
    = 3.96 > D = 3.6. tindell1994 looks at instance 0 only, with 130-bit frames: 3 x 1.04 = 3.12.
    """
    specs = [
        MessageSpec("A", 8, F("2.6"), F("2.6")),
        MessageSpec("B", 8, F(4), F(4)),
        MessageSpec("C", 8, F("3.6"), F("3.6")),
    ]
    davis = analyze(specs, 125_000, "davis2007", 11, blocking="lower-priority")
    tindell = analyze(specs, 125_000, "tindell1994", 11, blocking="lower-priority")
    assert [r.response_time_ms for r in davis] == [F("2.16"), F("3.24"), F("3.96")]
    assert [r.schedulable for r in davis] == [True, True, False]
    assert [r.response_time_ms for r in tindell] == [F("2.08"), F("3.12"), F("3.12")]
    assert all(r.schedulable for r in tindell)


def test_unbounded_busy_period_gives_none_and_is_unschedulable() -> None:
    # Two 8-byte messages every 0.2 ms at 1 Mbit/s need 2 x 0.135 ms per 0.2 ms: overload.
    specs = [MessageSpec("a", 8, F("0.2"), 5), MessageSpec("b", 8, F("0.2"), 5)]
    first, second = analyze(specs, 1_000_000, id_bits=11)
    assert first.response_time_ms is not None and first.schedulable
    assert second.response_time_ms is None and not second.schedulable
    assert second.deadline_ms == 5


def test_response_time_reported_beyond_deadline() -> None:
    spec = MessageSpec("late", 8, period_ms=10, deadline_ms=F("0.1"))
    (result,) = analyze([spec], 125_000, id_bits=11)
    assert result.response_time_ms == 2 * F("1.08")
    assert not result.schedulable


def test_priority_field_orders_and_output_follows_input(tmp_path: Path) -> None:
    path = tmp_path / "set.csv"
    path.write_text(
        "name,size_bytes,jitter_ms,period_ms,deadline_ms,priority\n"
        "slow,8,0,10,10,7\nfast,8,0,1,1,2\n"
    )
    specs = load_csv(path)
    results = analyze(specs, 1_000_000, id_bits=11, blocking="lower-priority")
    assert [r.name for r in results] == ["slow", "fast"]
    assert results[1].response_time_ms == F("0.27")  # "fast" is above: blocked once by "slow"
    swapped = analyze(specs[::-1], 1_000_000, id_bits=11, blocking="lower-priority")
    assert swapped == results[::-1]


def test_fd_frames_are_analysed_with_davis2007_only() -> None:
    spec = MessageSpec("big", 64, period_ms=10, deadline_ms=10)
    (result,) = analyze([spec], 1_000_000, fd=True)
    assert result.response_time_ms == 2 * frame_bits(64, 29, fd=True) * F(1, 1000)
    with pytest.raises(ValueError, match=r"0\.\.8"):
        analyze([spec], 1_000_000)
    with pytest.raises(ValueError, match="FD"):
        analyze([spec], 1_000_000, "tindell1994", fd=True)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"bitrate": 0}, "bitrate"),
        ({"method": "rta"}, "method"),
        ({"id_bits": 12}, "id_bits"),
        ({"blocking": "none"}, "blocking"),
    ],
)
def test_invalid_parameters(kwargs: dict[str, object], match: str) -> None:
    arguments: dict[str, object] = {"specs": [MessageSpec("a", 1, 1, 1)], "bitrate": 500_000}
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        analyze(**arguments)  # type: ignore[arg-type]


def test_duplicate_names_and_priorities_are_rejected() -> None:
    with pytest.raises(ValueError, match="twice"):
        analyze([MessageSpec("a", 1, 1, 1), MessageSpec("a", 1, 2, 2)], 500_000)
    with pytest.raises(ValueError, match="priority 3"):
        analyze([MessageSpec("a", 1, 1, 1, 0, 3), MessageSpec("b", 1, 2, 2, 0, 3)], 500_000)
    with pytest.raises(ValueError, match="no priority"):
        analyze([MessageSpec("a", 1, 1, 1, 0, 3), MessageSpec("b", 1, 2, 2)], 500_000)


@settings(max_examples=150, deadline=None)
@given(
    specs=message_sets(max_size=8),
    bitrate=st.sampled_from(BITRATES),
    id_bits=st.sampled_from((11, 29)),
    blocking=st.sampled_from(("max-frame", "lower-priority")),
)
def test_davis2007_never_below_tindell1994(
    specs: list[MessageSpec], bitrate: int, id_bits: int, blocking: str
) -> None:
    davis = analyze(specs, bitrate, "davis2007", id_bits, blocking=blocking)  # type: ignore[arg-type]
    tindell = analyze(specs, bitrate, "tindell1994", id_bits, blocking=blocking)  # type: ignore[arg-type]
    for d, t in zip(davis, tindell, strict=True):
        if d.response_time_ms is not None:
            assert t.response_time_ms is not None
            assert d.response_time_ms >= t.response_time_ms
        assert not (d.schedulable and not t.schedulable)


def test_davis2007_never_below_tindell1994_on_sae() -> None:
    specs = load_csv(SAE_CSV)
    for bitrate in BITRATES:
        for d, t in zip(
            analyze(specs, bitrate, "davis2007", 11),
            analyze(specs, bitrate, "tindell1994", 11),
            strict=True,
        ):
            assert d.response_time_ms is None or (
                t.response_time_ms is not None and d.response_time_ms >= t.response_time_ms
            )
