"""The roster ("Roster: who uses what, for a node that joins a running bus"): a joined node asks,
the CAN-ECB lists every (TxNode, role, channel) from the cursor on, page by page, in UID order,
and ends each page with RosterEnd naming the asker. Frames built from docs/protocol.md only."""

from __future__ import annotations

import asyncio
import time

from ups import name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import PUB_BIND, SUB_BIND, Roster, RosterEnd, Uses
from ._wire import RawNode, Wire

PAGE = 32  # "at least 32 Uses frames, whole channels"
RATE, BURST = 200, 48  # "at most 200 roster frames a second, 48 back to back"


async def _roster(raw: Wire, node: RawNode, cursor: int = 0) -> tuple[list[Uses], RosterEnd]:
    """Ask from ``cursor``; the Uses heard before the RosterEnd that answers ``node``."""
    assert node.txnode is not None
    since = raw.send(Roster(node.txnode, cursor))
    i, end = await raw.expect(
        lambda f: isinstance(f, RosterEnd) and f.txnode == node.txnode, since=since, timeout=5
    )
    return [f for f in raw.heard(since, i) if isinstance(f, Uses)], end


async def test_the_roster_lists_who_subscribes_and_publishes(raw: Wire, can_ecb: CanEcb) -> None:
    sub, pub, asker = RawNode(raw, 0x7201), RawNode(raw, 0x7202), RawNode(raw, 0x7203)
    t_sub, t_pub = await sub.join(), await pub.join()
    await asker.join()
    speed, brake = name_to_uid("roster/speed"), name_to_uid("roster/brake")
    await sub.ask(SUB_BIND, speed)
    await pub.ask(PUB_BIND, speed)
    await pub.ask(PUB_BIND, brake)
    uses, end = await _roster(raw, asker)
    assert end.done and end.next == 0
    expected = [Uses(False, t_sub, speed), Uses(True, t_pub, speed), Uses(True, t_pub, brake)]
    assert uses == sorted(expected, key=lambda u: (u.uid, u.publish, u.txnode))
    # from a cursor: only the channels from that UID on
    later, end = await _roster(raw, asker, max(speed, brake))
    assert end.done and {u.uid for u in later} == {max(speed, brake)}


async def test_a_long_roster_comes_in_pages_that_add_up(raw: Wire, can_ecb: CanEcb) -> None:
    node, asker = RawNode(raw, 0x7211), RawNode(raw, 0x7212)
    t = await node.join()
    await asker.join()
    uids = [name_to_uid(f"roster/c{n}") for n in range(PAGE + 10)]
    for uid in uids:
        await node.ask(SUB_BIND, uid)
    pages, cursor, seen = 0, 0, []
    while True:
        uses, end = await _roster(raw, asker, cursor)
        pages += 1
        assert len(uses) >= PAGE or end.done
        assert all(u.uid >= cursor for u in uses)
        seen += uses
        if end.done:
            break
        assert end.next > max(u.uid for u in uses)
        cursor = end.next
    assert pages == 2
    assert seen == [Uses(False, t, uid) for uid in sorted(uids)]  # each once, in UID order


async def test_a_roster_from_a_txnode_nobody_holds_is_not_answered(
    raw: Wire, can_ecb: CanEcb
) -> None:
    node = RawNode(raw, 0x7221)
    await node.join()
    since = raw.send(Roster(0x55, 0))
    await raw.expect_none((Uses, RosterEnd), since=since, window=0.5)
    _, end = await _roster(raw, node)  # and the node that holds its TxNode is answered
    assert end.done


async def test_a_flood_of_rosters_takes_no_more_of_the_bus_than_the_rate(
    raw: Wire, can_ecb: CanEcb
) -> None:
    """Rosters asked back to back, for a second: the CAN-ECB sends at most BURST frames plus
    RATE a second of them (an upper bound: a busy machine only sends fewer)."""
    node, asker = RawNode(raw, 0x7231), RawNode(raw, 0x7232)
    await node.join()
    t = await asker.join()
    for n in range(PAGE):
        await node.ask(SUB_BIND, name_to_uid(f"roster/flood{n}"))
    since = raw.mark()
    started = time.monotonic()
    while time.monotonic() - started < 1.0:
        raw.send(Roster(t, 0))
        await asyncio.sleep(0.01)  # a flood of about 100 requests a second
    elapsed = time.monotonic() - started
    await asyncio.sleep(0.3)  # a window: what it still sends within it counts too
    sent = len(raw.find((Uses, RosterEnd), since))
    assert sent <= BURST + RATE * (elapsed + 0.3) + 1
    assert can_ecb.stats()["roster_replaced"] > 0  # one request waits per TxNode
