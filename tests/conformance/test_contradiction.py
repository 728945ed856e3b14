"""The contradiction rule ("Binding": every node; "More than one CAN-ECB": the CAN-ECB)."""

from __future__ import annotations

from ups import Node, Subscription, name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import PUB_BIND, SUB_BIND, Bind, Event, Request
from ._wire import RawNode, Wire, bound_etag, txnode_of

NAME = "conformance/contradiction"
UID = name_to_uid(NAME)
OTHER = name_to_uid("conformance/contradiction/other")
NODE_ID = 0xC0DE


async def _subscribed(raw: Wire, node: Node, sender: RawNode) -> tuple[Subscription, int, int]:
    """The node subscribes to NAME; (subscription, node's TxNode, etag), once an event of the
    raw sender on that etag has reached the subscription."""
    t_node = await txnode_of(raw, NODE_ID)
    sub = await node.subscribe(NAME)
    etag = await bound_etag(raw, Request(SUB_BIND, t_node, UID))
    assert sender.txnode is not None
    raw.send(Event(0x80, sender.txnode, etag, b"\x01"))
    assert (await sub.get_msg(timeout=2.0)).data == b"\x01"
    return sub, t_node, etag


async def _rebound(raw: Wire, t_node: int, etag: int, since: int) -> None:
    """Wait for the node's SUB_BIND after ``since`` and for the Bind that answers it."""
    i_request, _ = await raw.expect(Request(SUB_BIND, t_node, UID), since=since)
    await raw.expect(Bind(etag, UID), since=i_request)


async def _delivery_resumes(
    raw: Wire, sub: Subscription, sender: int, etag: int, *also: Event
) -> None:
    """Send numbered events (0x10, 0x11, ...) on ``etag``, each after the frames ``also``,
    until one is delivered; the first delivered event must be one of them.

    The node receives the etag again once it has handled the Bind and programmed its filter;
    the wire cannot tell when that is, so this polls (bounded, 2 s)."""
    for number in range(0x10, 0x74):
        raw.send(*also, Event(0x80, sender, etag, bytes([number])))
        try:
            msg = await sub.get_msg(timeout=0.02)
        except TimeoutError:
            continue
        assert msg.data[0] >= 0x10, f"{msg.data.hex()} delivered: it was sent before re-binding"
        break
    else:
        raise AssertionError("no event delivered after the node re-bound")
    # and whatever comes next is one of ours too, in order (the first delivered may be one sent
    # before ``number``, late under load: order is against what was delivered)
    last = msg.data[0]
    while sub.pending:
        now = (await sub.get_msg(timeout=0)).data[0]
        assert last < now <= number, f"{now:#x} after {last:#x} (sent up to {number:#x})"
        last = now


async def test_node_stops_using_an_etag_bound_to_another_uid_until_it_rebinds(
    raw: Wire, can_ecb: CanEcb, channel: str
) -> None:
    sender = RawNode(raw, 0xC0DF)
    ts = await sender.join()
    async with Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10) as node:
        sub, t_node, etag = await _subscribed(raw, node, sender)

        # a forged Bind gives the node's etag to another UID; events follow at once
        forged = raw.send(
            Bind(etag, OTHER), Event(0x80, ts, etag, b"\x02"), Event(0x80, ts, etag, b"\x03")
        )
        await _rebound(raw, t_node, etag, forged)
        await _delivery_resumes(raw, sub, ts, etag)


async def test_node_stops_using_its_uids_etag_when_the_uid_is_bound_elsewhere(
    raw: Wire, can_ecb: CanEcb, channel: str
) -> None:
    sender = RawNode(raw, 0xC0E0)
    ts = await sender.join()
    async with Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10) as node:
        sub, t_node, etag = await _subscribed(raw, node, sender)
        elsewhere = 0x3ABC
        assert elsewhere != etag

        forged = raw.send(
            Bind(elsewhere, UID),
            Event(0x80, ts, etag, b"\x02"),
            Event(0x80, ts, elsewhere, b"\x03"),
        )
        await _rebound(raw, t_node, etag, forged)
        # adopts nothing from the forged Bind: the other etag is never this channel
        await _delivery_resumes(raw, sub, ts, etag, Event(0x80, ts, elsewhere, b"\x05"))
        # once more, then a last event on etag: nothing from the other etag comes before it
        raw.send(Event(0x80, ts, elsewhere, b"\x05"), Event(0x80, ts, etag, b"\xff"))
        while (msg := await sub.get_msg(timeout=2.0)).data != b"\xff":
            assert msg.data[0] >= 0x10, f"{msg.data.hex()} delivered from the other etag"


async def test_ecb_answers_a_contradicting_bind_with_its_own_binds(
    raw: Wire, can_ecb: CanEcb
) -> None:
    node = RawNode(raw, 0xC0E1)
    await node.join()
    u1, u2, u3 = (name_to_uid(f"conformance/contradiction/{n}") for n in "123")
    e1 = (await node.ask(SUB_BIND, u1)).etag
    e2 = (await node.ask(PUB_BIND, u2)).etag
    free = 0x3ABC
    assert free not in (e1, e2)

    # both the etag and the UID are bound otherwise: both Binds of the table
    since = raw.send(Bind(e1, u2))
    await raw.expect(Bind(e1, u1), since=since)
    await raw.expect(Bind(e2, u2), since=since)

    # the etag is another UID's
    since = raw.send(Bind(e1, u3))
    await raw.expect(Bind(e1, u1), since=since)

    # the UID has another etag
    since = raw.send(Bind(free, u2))
    await raw.expect(Bind(e2, u2), since=since)

    # and the table is unchanged
    assert (await node.ask(SUB_BIND, u2)).etag == e2
    assert (await node.ask(SUB_BIND, u1)).etag == e1
