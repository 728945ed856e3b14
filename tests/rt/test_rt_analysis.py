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

# Table 1 of paper 000 (Tindell & Burns 1994 on the SAE benchmark): every row and every column, R
# in ms at 125, 250, 500 and 1000 kbit/s; a trailing "x" marks a missed deadline, "-" a message
# with no bound (its higher-priority messages load the bus fully: at 125 kbit/s from row 21 on).
# Section 4.2: R_m = w_m + C_m, the message's own queuing jitter J_m left out of (2) and "the rest
# of the calculation intact", i.e. w_m = B_m + sum_{k in hp(m)} ceil((w_m + J_k + tau_bit) / T_k)
# C_k with the higher-priority messages' jitter J_k; blocking by one 8-byte frame (130 bits); C_m
# from equation (1) with the quotient rounded down (63 bits for one byte); tau_bit = 1/bitrate.
# The copy of paper 000 in shared/papers withholds these columns, so the figures were computed
# from that recurrence outside ups.rt (exact fractions) and agree with everything the text gives:
# 0.772 ms for the first row at 250 kbit/s, and each row is the row above plus C_m wherever no
# higher-priority message is queued twice. Where one is, jitter matters: 53 at 125 kbit/s and 27
# at 250 kbit/s are derived by hand below.
TABLE_1 = """
14  1.544     0.772     0.386     0.193
9   2.048     1.024     0.512     0.256
49  2.552     1.276     0.638     0.319
42  3.056     1.528     0.764     0.382
8   3.560     1.780     0.890     0.445
7   4.064     2.032     1.016     0.508
43  4.568     2.284     1.142     0.571
11  5.072x    2.536     1.268     0.634
32  9.104x    2.788     1.394     0.697
29  10.112x   3.040     1.520     0.760
30  15.152x   3.292     1.646     0.823
53  25.232x   3.544     1.772     0.886
48  29.768x   3.796     1.898     0.949
46  39.344x   4.048     2.024     1.012
44  39.848x   4.300     2.150     1.075
40  70.088x   4.552     2.276     1.138
39  85.208x   4.804     2.402     1.201
27  95.288x   7.072     2.528     1.264
38  190.040x  7.324     2.654     1.327
37  1095.224x 7.576     2.780     1.390
52  -         7.828     2.906     1.453
26  -         8.080     3.032     1.516
35  -         8.332     3.158     1.579
51  -         8.584     3.284     1.642
22  -         8.836     3.410     1.705
34  -         9.088     3.536     1.768
20  -         9.340     3.662     1.831
50  -         9.592     3.788     1.894
31  -         9.844     3.914     1.957
47  -         12.616    4.040     2.020
28  -         12.868    4.166     2.083
19  -         13.120    4.292     2.146
25  -         13.372    4.418     2.209
17  -         13.624    4.544     2.272
45  -         13.876    4.670     2.335
24  -         14.128    4.796     2.398
16  -         14.380    4.922     2.461
18  -         14.632    6.056     2.524
41  -         14.884    6.182     2.587
23  -         17.152    6.308     2.650
15  -         17.404    6.434     2.713
6   -         17.656    6.560     2.776
4   -         17.908    6.686     2.839
2   -         18.160    6.812     2.902
1   -         18.412    6.938     2.965
12  -         18.664    7.064     3.028
10  -         18.916    7.190     3.091
36  -         19.168    7.316     3.154
33  -         19.420    7.442     3.217
13  -         19.672    7.568     3.280
5   -         22.444    7.694     3.343
3   -         22.696    7.820     3.406
21  -         22.948    7.946     3.469
"""
BITRATES = (125_000, 250_000, 500_000, 1_000_000)


def _table_1() -> list[tuple[str, list[tuple[Fraction | None, bool]]]]:
    rows = []
    for line in TABLE_1.strip().splitlines():
        name, *cells = line.split()
        assert len(cells) == len(BITRATES), name
        rows.append(
            (
                name,
                [
                    (None, False) if cell == "-" else (F(cell.rstrip("x")), not cell.endswith("x"))
                    for cell in cells
                ],
            )
        )
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
    """Every cell of the column: all 53 messages, response time and deadline mark."""
    table = _table_1()
    assert len(table) == 53
    results = analyze(load_csv(SAE_CSV), BITRATES[column], "tindell1994", id_bits=11)
    got = [(r.name, r.response_time_ms, r.schedulable) for r in results]
    expected = [(name, *cells[column]) for name, cells in table]
    assert got == expected


def test_table_1_message_53_at_125_kbits_by_hand() -> None:
    """Row 12 at 125 kbit/s: tau = 8 us, C = 63 tau = 0.504 ms, B = 130 tau = 1.04 ms.

    Above 53 are 14 (T = 50), eight 5 ms messages (J = 0.2 for 9, 49, 42, else 0.1) and 29, 30
    (T = 10, J = 0.3, 0.4). Counting instances (14, each 5 ms one, 29, 30): w = 1.04 + 11 C =
    6.584 -> (1, 2, 1, 1): 10.616 -> (1, 3, 2, 2): 15.656 -> (1, 4, 2, 2): 19.688; there 30 comes a
    third time only through its jitter (19.688 + 0.4 + 0.008 > 20): 20.192 -> (1, 5, 3, 3): 24.728,
    a fixed point, so R = 24.728 + 0.504 = 25.232 (without J_k it stops at 19.688: 20.192).
    """
    results = analyze(load_csv(SAE_CSV), 125_000, "tindell1994", id_bits=11)
    assert results[11].name == "53"
    assert results[11].response_time_ms == F("25.232")
    c = 63 * F(8, 1000)
    assert results[11].response_time_ms == F("1.04") + (1 + 8 * 5 + 2 * 3) * c + c


def test_table_1_message_27_at_250_kbits_by_hand() -> None:
    """Row 18 at 250 kbit/s: tau = 4 us, C = 0.252 ms, B = 0.52 ms; 17 messages above.

    w = 0.52 + 17 C = 4.804; 9, 49 and 42 (J = 0.2) come again (4.804 + 0.2 + 0.004 > 5):
    w = 5.56, and then the other five 5 ms messages (5.56 + 0.1 + 0.004 > 5): w = 6.82, a fixed
    point (30: 6.82 + 0.4 + 0.004 < 10), so R = 7.072 (5.056 if the J_k were left out).
    """
    results = analyze(load_csv(SAE_CSV), 250_000, "tindell1994", id_bits=11)
    assert results[17].name == "27"
    assert results[17].response_time_ms == F("0.52") + (17 + 8) * F("0.252") + F("0.252")


def test_table_1_rows_add_one_frame_each_where_nothing_recurs() -> None:
    """Section 4.2: each row is the row above plus C_m while no message is queued twice.

    That holds for every row at 1000 kbit/s, for rows 1..37 at 500 kbit/s (at row 38, message
    18, w_m + J_k + tau_bit first exceeds 5 ms) and for rows 1..17 at 250 kbit/s (row 18, message
    27: see the test above).
    """
    for bitrate, rows in ((250_000, 17), (500_000, 37), (1_000_000, 53)):
        tau = F(1000, bitrate)
        results = analyze(load_csv(SAE_CSV), bitrate, "tindell1994", id_bits=11)[:rows]
        for row, result in enumerate(results, start=1):
            assert result.response_time_ms == (130 + 63 * row) * tau, (bitrate, row)


def test_tindell1994_leaves_out_own_jitter_but_counts_higher_priority_jitter() -> None:
    specs = load_csv(SAE_CSV)
    without = [MessageSpec(s.name, s.size_bytes, s.period_ms, s.deadline_ms) for s in specs]
    for bitrate in BITRATES:
        results = analyze(specs, bitrate, "tindell1994", 11)
        for index in range(len(specs)):
            # J_m of message m alone does not change R_m (it only delays lower-priority ones).
            own_zero = [*specs[:index], without[index], *specs[index + 1 :]]
            assert analyze(own_zero, bitrate, "tindell1994", 11)[index] == results[index]
        assert analyze(specs, bitrate, "davis2007", 11) != analyze(
            without, bitrate, "davis2007", 11
        )
    for bitrate in BITRATES[:2]:  # where some w_m + J_k + tau_bit crosses a period T_k
        assert analyze(specs, bitrate, "tindell1994", 11) != analyze(
            without, bitrate, "tindell1994", 11
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
