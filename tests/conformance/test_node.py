"""Our node from the document's point of view: its answer to Hello, and its whole life
(join, bind, events, move, contradiction) against a raw CAN-ECB written from the tables."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import TypeVar

import can
import pytest

from ups import Node, name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import (
    CLAIM,
    PUB_BIND,
    SUB_BIND,
    UNSUB,
    Assign,
    Bind,
    Census,
    Declare,
    Event,
    Frame,
    Grant,
    Hello,
    Knock,
    Offer,
    PubAt,
    Query,
    Request,
    Stage,
    SubAt,
    ident,
    nibbles,
)
from ._wire import Wire, bound_etag, txnode_of

NODE_ID = 0x0123_4567_89AB_CDEF
T = TypeVar("T")


def _from(txnode: int) -> Callable[[Frame], bool]:
    """Matches the management frames a joined node sends from ``txnode``."""

    def match(frame: Frame) -> bool:
        return isinstance(frame, Request | SubAt | PubAt) and frame.txnode == txnode

    return match


async def test_node_answers_hello_with_claim_and_its_bindings(
    raw: Wire, can_ecb: CanEcb, channel: str
) -> None:
    sub_only, pub_only, both = (f"conformance/hello/{n}" for n in ("sub", "pub", "both"))
    u_sub, u_pub, u_both = map(name_to_uid, (sub_only, pub_only, both))
    async with Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10) as node:
        t = await txnode_of(raw, NODE_ID)
        await node.subscribe(sub_only, both)
        await node.publish(pub_only, b"\x01")
        await node.publish(both, b"\x02")
        e_sub = await bound_etag(raw, Request(SUB_BIND, t, u_sub))
        e_pub = await bound_etag(raw, Request(PUB_BIND, t, u_pub))
        e_both = await bound_etag(raw, Request(SUB_BIND, t, u_both))
        # publishing a channel it already relies on needs no request
        assert not raw.find(Request(PUB_BIND, t, u_both))
        await raw.expect(PubAt(t, e_both, u_both))

        since = raw.send(Hello(0x1234_5678))
        expected = {
            SubAt(t, e_sub, u_sub),
            PubAt(t, e_pub, u_pub),
            SubAt(t, e_both, u_both),
            PubAt(t, e_both, u_both),
        }
        i_claim, _ = await raw.expect(Request(CLAIM, t, NODE_ID), since=since)
        for frame in expected:
            await raw.expect(frame, since=i_claim)
        answer = raw.find(_from(t), since)
        assert answer[0] == Request(CLAIM, t, NODE_ID), "CLAIM first"
        assert set(answer[1:]) == expected and len(answer) == 5


async def test_node_declares_its_streams_again_after_hello(
    raw: Wire, can_ecb: CanEcb, channel: str
) -> None:
    name = "conformance/hello/stream"
    uid = name_to_uid(name)
    async with Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10) as node:
        t = await txnode_of(raw, NODE_ID)
        priority = await node.declare(name, period_ms=10, deadline_ms=5, size_bytes=1)
        etag = await bound_etag(raw, Request(PUB_BIND, t, uid))
        declare = Declare(t, etag, 1, 100, 50, 0)  # units of 100 us
        await raw.expect(declare)
        await raw.expect(Grant(etag, t, priority))

        since = raw.send(Hello(0x1234_5678))
        i_claim, _ = await raw.expect(Request(CLAIM, t, NODE_ID), since=since)
        await raw.expect(PubAt(t, etag, uid), since=i_claim)
        await raw.expect(declare, since=i_claim)
        # and it publishes at the granted priority
        since = raw.mark()
        await node.publish(name, b"\x01")
        await raw.expect(Event(priority, t, etag, b"\x01"), since=since)


async def test_node_answers_at_most_one_hello_per_second(
    raw: Wire, can_ecb: CanEcb, channel: str
) -> None:
    async with Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10) as node:
        t = await txnode_of(raw, NODE_ID)
        await node.subscribe("conformance/hello/gap")
        await bound_etag(raw, Request(SUB_BIND, t, name_to_uid("conformance/hello/gap")))
        loop = asyncio.get_running_loop()

        start = raw.mark()
        for i in range(10):  # a burst of 10 Hellos within 0.2 s
            raw.send(Hello(0x4000 + i))
            await asyncio.sleep(0.02)  # pacing of the burst, not a synchronisation
        burst_end = loop.time()
        claim = Request(CLAIM, t, NODE_ID)
        await raw.expect(claim, since=start)
        with contextlib.suppress(AssertionError):  # the window ends 1.5 s after the burst
            await raw.expect_none(
                lambda f: f == claim and len(raw.find(claim, start)) > 2,
                since=start,
                window=burst_end + 1.5 - loop.time(),
            )
        claims = [h.at for h in raw.log[start:] if h.frame == claim and h.at <= burst_end + 1.5]
        assert 1 <= len(claims) <= 2, f"{len(claims)} CLAIMs"
        # "one that arrives sooner is answered when the second has passed"
        assert len(claims) == 2, "the Hellos of the burst after the first were never answered"
        assert claims[1] - claims[0] >= 0.95


async def test_node_ignores_foreign_frames_on_its_etag(
    raw: Wire, can_ecb: CanEcb, channel: str
) -> None:
    name = "conformance/node/foreign"
    async with Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10) as node:
        t = await txnode_of(raw, NODE_ID)
        sub = await node.subscribe(name)
        etag = await bound_etag(raw, Request(SUB_BIND, t, name_to_uid(name)))
        event_id = ident(0x80, 0x33, etag)
        raw.send(
            can.Message(arbitration_id=event_id, is_remote_frame=True, dlc=2),
            can.Message(arbitration_id=event_id, data=bytes(12), is_fd=True),  # > 8 bytes
            can.Message(arbitration_id=event_id, data=b"\xee", is_error_frame=True),
            can.Message(arbitration_id=etag & 0x7FF, data=b"\x11", is_extended_id=False),
            Event(0x80, 0x33, etag, b"\x42"),
        )
        # the legitimate event, sent last, comes first: none of the foreign frames came before
        assert (await sub.get_msg(timeout=2.0)).data == b"\x42"
        assert not sub.pending


@contextlib.asynccontextmanager
async def raw_ecb_node(raw: Wire, channel: str, txnode: int) -> AsyncIterator[Node]:
    """Our node, joined through the test acting as the CAN-ECB: Census, Stages, Assign."""
    node = Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10)
    starting = asyncio.create_task(node.start())
    try:
        await raw.expect(Knock, timeout=3.0)
        since = raw.send(Census(0))
        for s, n in enumerate(nibbles(NODE_ID)):
            await raw.expect(Stage(0, s, n), since=since)
        since = raw.send(Offer(txnode, NODE_ID))
        await raw.expect(Request(CLAIM, txnode, NODE_ID), since=since)
        raw.send(Assign(txnode, NODE_ID))
        await asyncio.wait_for(starting, 5.0)
        yield node
    finally:
        starting.cancel()
        await node.close()


async def raw_bind(raw: Wire, request: Request, etag: int, use: Awaitable[T]) -> T:
    """Run ``use`` (a subscribe or publish of the node), answer its ``request`` with
    Bind(etag, uid), and return what ``use`` returns."""
    task = asyncio.ensure_future(use)
    since = raw.mark()
    await raw.expect(request, since=since)
    raw.send(Bind(etag, request.value))
    return await asyncio.wait_for(task, 5.0)


async def until_sent(raw: Wire, node: Node, name: str, txnode: int, etag: int) -> None:
    """Publish numbered events until one is on the wire (the node sends again once it has
    handled the Bind, which the wire cannot tell): bounded polling, 2 s."""
    for number in range(0x10, 0x74):
        since = raw.mark()
        await node.publish(name, bytes([number]))
        with contextlib.suppress(AssertionError):
            await raw.expect(Event(0x80, txnode, etag, bytes([number])), since=since, timeout=0.02)
            return
    raise AssertionError("the node never sent an event after re-binding")


async def test_node_joins_and_binds_with_a_raw_ecb(raw: Wire, channel: str) -> None:
    node = Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10)
    starting = asyncio.create_task(node.start())
    try:
        await raw.expect(Knock, timeout=3.0)

        # Census: sixteen Stage frames, one per nibble, no data
        since = raw.send(Census(0))
        for s, n in enumerate(nibbles(NODE_ID)):
            await raw.expect(Stage(0, s, n), since=since)
        assert sorted(set(raw.find(Stage, since))) == [
            Stage(0, s, n) for s, n in enumerate(nibbles(NODE_ID))
        ]
        # a Query for a prefix it does not have: no answer; one for its prefix: the rest (an
        # answer to the first would come before the second's, which are awaited)
        since = raw.send(Query(1, (0xF,)), Query(2, nibbles(NODE_ID, 5)))
        for s in range(5, 16):
            await raw.expect(Stage(2, s, nibbles(NODE_ID)[s]), since=since)
        assert raw.find(Stage, since) == [Stage(2, s, nibbles(NODE_ID)[s]) for s in range(5, 16)]

        # an Offer for another id: no CLAIM; one for its id: CLAIM from the offered TxNode (a
        # CLAIM answering the first would come before it)
        since = raw.send(Offer(0x04, NODE_ID ^ 1), Offer(0x05, NODE_ID))
        i_claim, _ = await raw.expect(Request(CLAIM, 0x05, NODE_ID), since=since)
        assert raw.find(Request, since, i_claim + 1) == [Request(CLAIM, 0x05, NODE_ID)]
        assert not starting.done(), "joined before its Assign"
        raw.send(Assign(0x05, NODE_ID))
        await asyncio.wait_for(starting, 5.0)

        # joined: it ignores Census, Query and Offer
        quiet = raw.send(Census(3), Query(4, nibbles(NODE_ID, 3)), Offer(0x0A, NODE_ID))

        # subscribe: SUB_BIND from TxNode 5, our Bind, then events of that etag are delivered
        name = "conformance/raw-ecb"
        uid = name_to_uid(name)
        sub = await raw_bind(raw, Request(SUB_BIND, 0x05, uid), 0x0123, node.subscribe(name))
        raw.send(Event(0x90, 0x11, 0x0123, b"hi"))
        msg = await sub.get_msg(timeout=2.0)
        assert (msg.channel.uid, msg.data, msg.priority, msg.source) == (uid, b"hi", 0x90, 0x11)
        assert not raw.find(Stage, quiet)
        assert not raw.find(Request(CLAIM, 0x0A, NODE_ID), quiet)

        # publishing the channel it relies on: PUB_AT, then the event
        since = raw.mark()
        await node.publish(name, b"\x07")
        i_at, _ = await raw.expect(PubAt(0x05, 0x0123, uid), since=since)
        await raw.expect(Event(0x80, 0x05, 0x0123, b"\x07"), since=i_at)

        # a channel it only publishes: PUB_BIND, our Bind, the event
        other = name_to_uid("conformance/raw-ecb/pub")
        since = raw.mark()
        await raw_bind(raw, Request(PUB_BIND, 0x05, other), 0x0124, node.publish(other, b"\x08"))
        await raw.expect(Event(0x80, 0x05, 0x0124, b"\x08"), since=since)

        # closing: UNSUB of its subscription
        since = raw.mark()
        await node.close()
        await raw.expect(Request(UNSUB, 0x05, uid), since=since)
    finally:
        starting.cancel()
        await node.close()


async def test_node_moves_when_assigned_another_txnode(raw: Wire, channel: str) -> None:
    async with raw_ecb_node(raw, channel, 0x05) as node:
        name = "conformance/raw-ecb/move"
        uid = name_to_uid(name)
        await raw_bind(raw, Request(SUB_BIND, 0x05, uid), 0x0123, node.subscribe(name))

        # "must move to t' at once ... and announce itself as after a Hello"
        since = raw.send(Assign(0x09, NODE_ID))
        i_claim, _ = await raw.expect(Request(CLAIM, 0x09, NODE_ID), since=since)
        await raw.expect(SubAt(0x09, 0x0123, uid), since=i_claim)
        since = raw.mark()
        await node.publish(name, b"\x08")
        await raw.expect(Event(0x80, 0x09, 0x0123, b"\x08"), since=since)
        assert not raw.find(_from(0x05), since)


async def test_node_sends_no_event_of_a_contradicted_channel_until_it_rebinds(
    raw: Wire, channel: str
) -> None:
    async with raw_ecb_node(raw, channel, 0x05) as node:
        name = "conformance/raw-ecb/contradicted"
        uid = name_to_uid(name)
        await raw_bind(raw, Request(PUB_BIND, 0x05, uid), 0x0123, node.publish(name, b"\x01"))

        since = raw.send(Bind(0x0123, name_to_uid("conformance/raw-ecb/other")))
        # it asks again (we do not answer yet) ...
        await raw.expect(Request(PUB_BIND, 0x05, uid), since=since)
        # ... and publishes nothing of the channel meanwhile
        for number in range(3):
            await node.publish(name, bytes([number]))
        await raw.expect_none(Event, since=since, window=0.15)

        # the etag was last heard as another channel's: the first answer is doubted ...
        answered = raw.send(Bind(0x0123, uid))
        await raw.expect(Request(PUB_BIND, 0x05, uid), since=answered)
        raw.send(Bind(0x0123, uid))  # ... the second counts
        await until_sent(raw, node, name, 0x05, 0x0123)
        assert not raw.find(lambda f: isinstance(f, Event) and f.data[0] < 0x10, since)


@pytest.mark.parametrize("victim_at", [6, 11])
@pytest.mark.parametrize("trigger", ["hello", "move"])
async def test_node_reports_no_contradicted_binding_in_its_announcement(
    raw: Wire, channel: str, trigger: str, victim_at: int
) -> None:
    """A node announces what it relies on (after Hello, or after moving to another TxNode); a
    contradicting Bind that arrives while it announces ends its reliance on that binding, so
    the rest of the announcement must not report it. (The victim is not among the first
    frames: those may already be in the controller's queue, which the document leaves open.)"""
    async with raw_ecb_node(raw, channel, 0x05) as node:
        names = [f"conformance/raw-ecb/announce/{n}" for n in range(12)]
        for etag, name in enumerate(names, start=0x0200):
            uid = name_to_uid(name)
            await raw_bind(raw, Request(SUB_BIND, 0x05, uid), etag, node.subscribe(name))
        victim = name_to_uid(names[victim_at])  # the order in which they are bound

        t = 0x05 if trigger == "hello" else 0x09
        since = raw.send(Hello(0x77) if trigger == "hello" else Assign(t, NODE_ID))
        await raw.expect(Request(CLAIM, t, NODE_ID), since=since)
        # a Bind contradicting the last channel, while the answer is being sent
        forged = raw.send(Bind(0x0200 + victim_at, name_to_uid("conformance/other")))
        i_ask, _ = await raw.expect(Request(SUB_BIND, t, victim), since=forged)
        await raw.expect_none(
            lambda f: isinstance(f, SubAt | PubAt) and f.uid == victim, since=i_ask, window=0.2
        )
