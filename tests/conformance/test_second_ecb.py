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
    raw: Wire, channel: str, tmp_path: Path
) -> None:
    async with serving_ecb(channel, tmp_path / "ecb.db"):
        await raw.expect(Hello)
        since = raw.send(Serving(HIGHEST), Knock())  # the other was first
        await raw.expect_none(ECB_FRAMES, since=since, window=0.6)


async def test_hello_of_a_lower_instance_during_recovery_makes_it_stand_by(
    raw: Wire, channel: str, tmp_path: Path
) -> None:
    async with serving_ecb(channel, tmp_path / "ecb.db"):
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
