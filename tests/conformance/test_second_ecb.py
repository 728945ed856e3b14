"""More than one CAN-ECB ("More than one CAN-ECB, and frames nobody should send"): a raw
"CAN-ECB" on the bus of our CAN-ECB."""

from __future__ import annotations

from pathlib import Path

from ups import name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import (
    ECB_FRAMES,
    SUB_BIND,
    Assign,
    Bind,
    Census,
    Grant,
    Hello,
    Knock,
    Probe,
    Serving,
    sub_bind,
)
from ._wire import RawNode, Wire, serving_ecb

HIGHEST = (1 << 64) - 1
UID = name_to_uid("conformance/second-ecb")


async def _joined(raw: Wire) -> RawNode:
    """A joined raw node: its Assign also tells that recovery is over."""
    node = RawNode(raw, 0x5EC0)
    await node.join()
    return node


async def test_hello_of_another_ecb_is_answered_with_serving(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    node = await _joined(raw)
    since = raw.send(Hello(0))  # a lower instance, but our CAN-ECB is past its recovery
    _, serving = await raw.expect(Serving, since=since)
    assert serving == Serving(instance)
    # it serves on
    assert (await node.ask(SUB_BIND, UID)).uid == UID


async def test_serving_of_a_higher_instance_is_answered_with_serving(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    node = await _joined(raw)
    since = raw.send(Serving(HIGHEST))
    await raw.expect(Serving(instance), since=since)
    assert (await node.ask(SUB_BIND, UID)).uid == UID


async def test_serving_of_a_lower_instance_makes_it_stand_by(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    node = await _joined(raw)
    assert node.txnode is not None
    since = raw.send(Serving(0), sub_bind(node.txnode, UID))
    await raw.expect_none(ECB_FRAMES, since=since, window=0.5)


async def test_serving_heard_during_recovery_makes_it_stand_by(
    raw: Wire, channel: str, tmp_path: Path, ecb_kind: str
) -> None:
    async with serving_ecb(channel, tmp_path / "ecb.db", ecb_kind):
        await raw.expect(Hello)
        since = raw.send(Serving(HIGHEST), Knock())  # the other was first
        await raw.expect_none(ECB_FRAMES, since=since, window=0.6)


async def test_hello_of_a_lower_instance_during_recovery_makes_it_stand_by(
    raw: Wire, channel: str, tmp_path: Path, ecb_kind: str
) -> None:
    async with serving_ecb(channel, tmp_path / "ecb.db", ecb_kind):
        await raw.expect(Hello)
        since = raw.send(Hello(0), Knock())
        await raw.expect_none(ECB_FRAMES, since=since, window=0.6)


async def test_other_ecb_frames_get_serving_at_most_once_per_second(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    node = await _joined(raw)
    since = raw.send(Census(5), Assign(0x33, 0xDEAD), Grant(0x20, 0x33, 0x02))
    first, _ = await raw.expect(Serving(instance), since=since)
    await raw.expect_none(Serving, since=first + 1, window=0.5)
    assert (await node.ask(SUB_BIND, UID)).uid == UID
    assert not raw.find(Bind(0x20, UID))


async def test_a_bind_it_did_not_send_and_that_contradicts_nothing_gets_serving(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """ "Bind that its table contradicts: it sends its own Binds ... anything else: it sends
    Serving (at most once per second)"."""
    node = await _joined(raw)
    since = raw.send(Bind(0x3ABD, name_to_uid("conformance/second-ecb/unknown")))
    await raw.expect(Serving(instance), since=since)
    assert (await node.ask(SUB_BIND, UID)).uid == UID


# --- Probe: a standing-by CAN-ECB asks, and claims nothing ------------------------------------


async def test_a_candidacy_ends_with_serving(raw: Wire, can_ecb: CanEcb, instance: int) -> None:
    """ "serving, once its candidacy has ended; it then sends Serving(its instance) at once"."""
    i_hello, _ = await raw.expect(Hello(instance))
    await raw.expect(Serving(instance), since=i_hello)


async def test_a_probe_is_answered_with_serving_and_never_makes_it_stand_by(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """A Probe of the lowest instance: a Serving would make it stand by, a Probe must not."""
    node = await _joined(raw)
    since = raw.send(Probe(0))
    first, _ = await raw.expect(Serving(instance), since=since)
    since = raw.send(Probe(0), Probe(1))  # within the Serving gap: answered when it has passed
    second, _ = await raw.expect(Serving(instance), since=since)
    assert raw.log[second].at - raw.log[first].at >= 0.99
    assert (await node.ask(SUB_BIND, UID)).uid == UID  # it serves on


async def test_a_probe_during_the_candidacy_changes_nothing(
    raw: Wire, channel: str, tmp_path: Path, ecb_kind: str
) -> None:
    """A candidate sends nothing for a Probe, and serves when its candidacy ends."""
    async with serving_ecb(channel, tmp_path / "ecb.db", ecb_kind, recovery=1.0):
        i_hello, hello = await raw.expect(Hello)
        since = raw.send(Probe(0), Knock())
        i_serving, _ = await raw.expect(Serving(hello.instance), since=since)
        assert raw.log[i_serving].at - raw.log[i_hello].at >= 0.99  # at the candidacy's end
        assert not raw.find(ECB_FRAMES, since=since, until=i_serving)
        await raw.expect(Census, since=since)  # and it serves the Knock


async def test_a_standing_by_can_ecb_probes_and_probes_do_not_keep_it_standing_by(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """ "A standing-by CAN-ECB sends Probe(its instance) every 2 s ... When it has heard no Hello
    or Serving of another instance for 4 s ... it sends Hello": another standing-by CAN-ECB's
    Probes, answered at once, do not keep it standing by."""
    await _joined(raw)
    since = raw.send(Serving(0))  # a lower instance serves: ours stands by
    rival = Probe(0)

    def answer(frame: object) -> None:
        if frame == Probe(instance):
            raw.send(rival)

    raw.handlers.append(answer)
    try:
        i_probe, _ = await raw.expect(Probe(instance), since=since, timeout=3.0)
        i_hello, _ = await raw.expect(Hello(instance), since=i_probe, timeout=4.0)
    finally:
        raw.handlers.remove(answer)
    assert raw.log[i_hello].at - raw.log[since].at >= 3.99  # the takeover time, from Serving(0)
    assert not raw.find(Serving(instance), since=since, until=i_hello)  # it never claimed


# --- a Serving is a claim: a standing-by CAN-ECB watches that requests are answered -------------

ANSWER = 2.5  #: Timers: "answer"


async def test_a_request_unanswered_while_it_stands_by_makes_it_serve_whatever_servings_say(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """ "A standing-by CAN-ECB ... that has heard a SUB_BIND, PUB_BIND or Knock go without its
    answer for the answer time (2.5 s) takes over, whatever Serving frames say ... and is
    wary": a Serving alone no longer makes it stand by."""
    node = await _joined(raw)
    assert node.txnode is not None
    raw.send(Serving(0))  # a forger's: ours stands by
    asked = raw.send(sub_bind(node.txnode, UID))
    raw.send(Serving(0))  # and again, before the takeover time
    i_hello, _ = await raw.expect(Hello(instance), since=asked, timeout=ANSWER + 1.0)
    assert raw.log[i_hello].at - raw.log[asked].at >= ANSWER - 0.01
    answers = [f for f in raw.find(ECB_FRAMES, since=asked, until=i_hello) if f != Probe(instance)]
    assert not answers  # it answered nothing meanwhile (it probed)
    await raw.expect(Serving(instance), since=i_hello)  # its candidacy ends
    since = raw.send(Serving(0))
    await raw.expect_none(Serving, since=since + 1, window=0.3)  # a claim alone: not answered
    assert (await node.ask(SUB_BIND, UID)).uid == UID  # it serves on


async def test_a_standing_by_can_ecb_that_hears_the_answers_stays_standing_by(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """The other CAN-ECB answers each request (here the test, as one would): ours stands by,
    probing, past the answer time."""
    node = await _joined(raw)
    assert node.txnode is not None
    since = raw.send(Serving(0))

    def serve(frame: object) -> None:  # the other CAN-ECB: it answers the Probe and the request
        if frame == Probe(instance):
            raw.send(Serving(0))

    raw.handlers.append(serve)
    try:
        asked = raw.send(sub_bind(node.txnode, UID), Bind(0x20, UID))
        i_probe, _ = await raw.expect(Probe(instance), since=asked, timeout=3.0)
        await raw.expect(Probe(instance), since=i_probe + 1, timeout=3.0)  # 2 s later
    finally:
        raw.handlers.remove(serve)
    assert raw.log[-1].at - raw.log[asked].at >= ANSWER - 0.6
    assert not raw.find(Hello(instance), since=since)
