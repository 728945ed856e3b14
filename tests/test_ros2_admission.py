"""What ``ups ros2`` takes from ROS (``ros2/_admit.py``), on a clock of our own: a topic's
token bucket (``burst`` back to back, then ``max_rate`` a second; the excess counted), and each
publisher's sequence numbers, whose gaps count as loss only within what the topic's rate could
have carried (a number that goes back or jumps further is counted once as a jump)."""

from __future__ import annotations

from ups.ros2 import attachment
from ups.ros2._admit import LOSS_WINDOW, MAX_SOURCES, Admission, Gate

GID = bytes(range(16))
OTHER = bytes(range(16, 32))
COUNTERS = ("no_attachment", "ros_lost", "ros_jumps", "rate_limited")


def admission() -> tuple[Admission, dict[str, int]]:
    counters = dict.fromkeys(COUNTERS, 0)
    return Admission(counters), counters


def test_a_burst_after_silence_goes_through_then_the_rate_holds() -> None:
    adm, counters = admission()
    gate = Gate.new(100.0, 20, now=0.0)
    # 1000 samples at once, after a silence: the burst
    assert sum(adm.admit(gate, None, 0.0) for _ in range(1000)) == 20
    assert counters["rate_limited"] == 980 and counters["no_attachment"] == 1000
    # one second of 1000 samples a second: max_rate of them (whatever the bucket held left)
    taken = sum(adm.admit(gate, None, i / 1000) for i in range(1, 1001))
    assert taken == 100
    # silence refills it, never beyond the burst
    assert sum(adm.admit(gate, None, 60.0) for _ in range(100)) == 20


def test_over_any_time_at_most_burst_plus_rate_times_time_go_through() -> None:
    adm, _ = admission()
    gate = Gate.new(37.5, 5, now=10.0)
    times = [10.0 + i * 0.0007 for i in range(20_000)]  # 14 s at 1428 samples a second
    taken = [t for t in times if adm.admit(gate, None, t)]
    assert len(taken) == 5 + int(37.5 * (times[-1] - times[0]))
    for start in range(0, len(taken), 7):  # every window [taken[start], taken[end]]
        for end in range(start, len(taken), 5):
            assert end - start + 1 <= 5 + 37.5 * (taken[end] - taken[start]) + 1e-9


def test_a_gap_is_loss_only_within_the_topics_credit() -> None:
    adm, counters = admission()
    gate = Gate.new(100.0, 20, now=0.0)
    sample = [attachment(n, 0, GID) for n in range(1, 8)]
    adm.admit(gate, sample[0], 1.0)  # the publisher's first: nothing to compare
    adm.admit(gate, sample[1], 1.01)
    adm.admit(gate, sample[4], 1.02)  # 3 and 4 skipped: 2 lost
    assert counters["ros_lost"] == 2 and counters["ros_jumps"] == 0
    adm.admit(gate, attachment(2**62, 0, GID), 1.03)  # forged: far beyond 100/s for 1 s
    assert counters["ros_lost"] == 2 and counters["ros_jumps"] == 1
    adm.admit(gate, sample[5], 1.04)  # the publisher's own next: back, a jump, followed again
    adm.admit(gate, sample[6], 1.05)
    assert counters["ros_lost"] == 2 and counters["ros_jumps"] == 2
    # two publishers are followed apart
    adm.admit(gate, attachment(500, 0, OTHER), 1.06)
    adm.admit(gate, attachment(501, 0, OTHER), 1.07)
    assert counters["ros_lost"] == 2 and counters["ros_jumps"] == 2


def test_forged_gaps_raise_ros_lost_by_at_most_the_topics_rate() -> None:
    """A forger sending gaps that fit the credit, as often as it likes, as many senders as it
    likes: ros_lost grows by at most max_rate a second after a first LOSS_WINDOW's worth."""
    adm, counters = admission()
    gate = Gate.new(100.0, 20, now=0.0)
    senders = [bytes([i]) * 16 for i in range(50)]
    seq = dict.fromkeys(senders, 1)
    for who in senders:
        adm.admit(gate, attachment(1, 0, who), 0.0)
    steps = 20_000
    for step in range(steps):  # 200 s, a forged sample every 10 ms, gaps of 1 to 500
        who = senders[step % len(senders)]
        seq[who] += 2 + step % 500
        adm.admit(gate, attachment(seq[who], 0, who), step * 0.01)
    elapsed = (steps - 1) * 0.01
    assert 0 < counters["ros_lost"] <= 100.0 * elapsed + 1e-6  # the credit starts empty
    assert counters["ros_jumps"] > 0
    # and after a silence, one forged gap takes at most LOSS_WINDOW seconds' worth
    before = counters["ros_lost"]
    adm.admit(gate, attachment(seq[senders[0]] + 10**9, 0, senders[0]), 10_000.0)
    assert counters["ros_lost"] == before and counters["ros_jumps"] > 0
    adm.admit(gate, attachment(seq[senders[1]] + 10**9, 0, senders[1]), 20_000.0)
    adm.admit(gate, attachment(seq[senders[1]] + 10**9 + 6001, 0, senders[1]), 20_000.0)
    assert counters["ros_lost"] - before == 100.0 * LOSS_WINDOW


def test_a_long_outage_of_a_real_publisher_is_loss() -> None:
    """A 50 Hz publisher whose link stalls 5 s: 250 numbers skipped, within the credit."""
    adm, counters = admission()
    gate = Gate.new(100.0, 20, now=0.0)
    for n in range(1, 501):  # 10 s at 50 Hz
        adm.admit(gate, attachment(n, 0, GID), n / 50)
    adm.admit(gate, attachment(751, 0, GID), 15.0)
    assert counters["ros_lost"] == 250 and counters["ros_jumps"] == 0


def test_the_oldest_publisher_is_forgotten_past_max_sources() -> None:
    adm, counters = admission()
    gate = Gate.new(100.0, 20, now=0.0)
    for i in range(MAX_SOURCES + 1):
        adm.admit(gate, attachment(1, 0, i.to_bytes(16, "little")), 100.0)
    newest, first = MAX_SOURCES.to_bytes(16, "little"), bytes(16)
    adm.admit(gate, attachment(9, 0, newest), 100.0)  # followed: 2..8 lost
    assert counters["ros_lost"] == 7
    # the first one was forgotten: its next number is a first again, neither loss nor jump
    adm.admit(gate, attachment(9, 0, first), 100.0)
    assert counters["ros_lost"] == 7 and counters["ros_jumps"] == 0
