"""Binding, events and real-time declarations ("Binding", "Real-time channels"): a raw joined
node and our real Node against our CAN-ECB."""

from __future__ import annotations

from ups import Node, name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import (
    BEST_EFFORT,
    FIRST_ETAG,
    LAST_ETAG,
    PUB_BIND,
    SUB_BIND,
    Bind,
    Declare,
    Event,
    Grant,
    Request,
)
from ._wire import RawNode, Wire, bound_etag, txnode_of


async def test_sub_bind_and_pub_bind_are_answered_with_binds(raw: Wire, can_ecb: CanEcb) -> None:
    node = RawNode(raw, 0x7701)
    await node.join()
    one, two = name_to_uid("conformance/one"), name_to_uid("conformance/two")

    first = await node.ask(SUB_BIND, one)
    assert FIRST_ETAG <= first.etag <= LAST_ETAG
    assert first.etag == FIRST_ETAG, "a new UID gets the lowest free etag"
    assert await node.ask(SUB_BIND, one) == first, "the same UID, the same etag"
    assert await node.ask(PUB_BIND, one) == first
    second = await node.ask(PUB_BIND, two)
    assert second.uid == two and second.etag != first.etag
    assert FIRST_ETAG <= second.etag <= LAST_ETAG


async def test_raw_events_reach_a_subscribed_node(raw: Wire, can_ecb: CanEcb, channel: str) -> None:
    name = "conformance/speed"
    uid = name_to_uid(name)
    sender = RawNode(raw, 0x7702)
    t_sender = await sender.join()
    etag = (await sender.ask(PUB_BIND, uid)).etag

    async with Node(can=f"virtual:{channel}", node_id=0x7703, join_timeout=10) as node:
        t_node = await txnode_of(raw, 0x7703)
        sub = await node.subscribe(name)
        # the node asked, and the Bind that answers it is on the bus before our events
        assert await bound_etag(raw, Request(SUB_BIND, t_node, uid)) == etag

        payloads = [(b"\x01\x02\x03", 0x90), (bytes(range(8)), 0x02), (b"", 0xFF)]
        for data, priority in payloads:
            raw.send(Event(priority, t_sender, etag, data))
        for data, priority in payloads:
            msg = await sub.get_msg(timeout=2.0)
            assert (msg.channel.uid, msg.data, msg.priority) == (uid, data, priority)
            assert msg.source == t_sender


async def test_a_nodes_publish_is_an_event_frame(raw: Wire, can_ecb: CanEcb, channel: str) -> None:
    fast, slow = "conformance/fast", "conformance/slow"
    async with Node(can=f"virtual:{channel}", node_id=0x7704, join_timeout=10) as node:
        t = await txnode_of(raw, 0x7704)
        node.set_priority(fast, 0x90)
        since = raw.mark()
        await node.publish(fast, b"\xaa\xbb")
        # PUB_BIND before its first event, then the event with priority | TxNode | etag
        etag = await bound_etag(raw, Request(PUB_BIND, t, name_to_uid(fast)), since=since)
        i_bind, _ = await raw.expect(Bind(etag, name_to_uid(fast)), since=since)
        await raw.expect(Event(0x90, t, etag, b"\xaa\xbb"), since=i_bind)

        since = raw.mark()
        await node.publish(slow, b"\x01")
        etag = await bound_etag(raw, Request(PUB_BIND, t, name_to_uid(slow)), since=since)
        await raw.expect(Event(BEST_EFFORT, t, etag, b"\x01"), since=since)


async def test_a_node_never_sends_events_at_management_priorities(
    raw: Wire, can_ecb: CanEcb, channel: str
) -> None:
    async with Node(can=f"virtual:{channel}", node_id=0x7705, join_timeout=10) as node:
        t = await txnode_of(raw, 0x7705)
        for priority, name in ((0x00, "conformance/p0"), (0x01, "conformance/p1")):
            node.set_priority(name, priority)
            since = raw.mark()
            await node.publish(name, b"\x42")
            etag = await bound_etag(raw, Request(PUB_BIND, t, name_to_uid(name)), since=since)
            await raw.expect(Event(0x02, t, etag, b"\x42"), since=since)


async def test_declare_is_granted_and_an_identical_declare_gets_the_same_grant(
    raw: Wire, can_ecb: CanEcb
) -> None:
    node = RawNode(raw, 0x7706)
    t = await node.join()
    etag = (await node.ask(PUB_BIND, name_to_uid("conformance/brake"))).etag
    # 1 byte every 10 ms, due within 5 ms, no jitter (units of 100 us)
    declare = Declare(t, etag, 1, 100, 50, 0)

    since = raw.send(declare)
    _, grant = await raw.expect(Grant, since=since)
    assert (grant.etag, grant.txnode) == (etag, t)
    assert 0x02 <= grant.priority <= 0x7F
    assert grant.priority == 0x02, "the only stream is first in the ordering"

    since = raw.send(declare)
    _, again = await raw.expect(Grant, since=since)
    assert again == grant
