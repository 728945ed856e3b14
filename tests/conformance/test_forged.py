"""Frames a forger sends (issue 32): which verdicts and refusals a node takes ("Refusals" in
*Joining* and *Binding*, "Which verdicts a node takes" in *Real-time channels*), what the
CAN-ECB answers to those it did not send ("More than one CAN-ECB, and frames nobody should
send"), and the binding quota (*Bounds*)."""

from __future__ import annotations

import asyncio
import contextlib

import pytest

from ups import BrokerUnavailable, Exhausted, Node, Unschedulable, name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import (
    CLAIM,
    PUB_BIND,
    SUB_BIND,
    Assign,
    Bind,
    Census,
    Declare,
    EtagsFull,
    Event,
    Failed,
    Frame,
    Grant,
    Hello,
    Knock,
    Limit,
    Offer,
    Refuse,
    Request,
    Stage,
    TxNodesFull,
    nibbles,
)
from ._wire import REFUSAL_WAIT, RawNode, Wire
from .test_node import NODE_ID, raw_bind, raw_ecb_node

UNBOUNDED = 0xFFFF  #: a Refuse's response: "unbounded or larger"
QUOTA = 1024  #: Bounds: bindings of size class 0 one node id may create


async def handled(raw: Wire, txnode: int) -> None:
    """A barrier: Hello, answered with CLAIM once every frame before it was handled (the first
    Hello of a node's life is answered at once)."""
    since = raw.send(Hello(0x4242))
    await raw.expect(Request(CLAIM, txnode, NODE_ID), since=since)


async def sent_at(raw: Wire, node: Node, name: str, etag: int, priority: int) -> None:
    """Publish numbered events until one is on the wire at ``priority`` (the node takes a
    verdict as it handles it, which the wire cannot tell): bounded polling, 2 s."""
    for number in range(0x20, 0x84):
        since = raw.mark()
        await node.publish(name, bytes([number]))
        with contextlib.suppress(AssertionError):
            await raw.expect(
                Event(priority, 0x05, etag, bytes([number])), since=since, timeout=0.02
            )
            return
    raise AssertionError(f"no event of {name} at priority {priority:#x}")


# --- our node: verdicts -----------------------------------------------------------------------


async def test_node_ignores_verdicts_for_a_stream_it_did_not_declare(
    raw: Wire, channel: str
) -> None:
    async with raw_ecb_node(raw, channel, 0x05) as node:
        name = "conformance/forged/undeclared"
        uid = name_to_uid(name)
        await raw_bind(raw, Request(PUB_BIND, 0x05, uid), 0x0123, node.publish(name, b"\x01"))
        raw.send(Grant(0x0123, 0x05, 0x02), Refuse(0x0123, 0x05, 0x05, 0x0123, UNBOUNDED))
        await handled(raw, 0x05)
        since = raw.mark()
        await node.publish(name, b"\x02")
        await raw.expect(Event(0x80, 0x05, 0x0123, b"\x02"), since=since)


async def test_node_answers_a_declaration_with_the_latest_verdict(raw: Wire, channel: str) -> None:
    """A Grant, then at once a Refuse: the answer is the Refuse. The node asks no more once a
    verdict came, and a Grant after the refusal is stray."""
    async with raw_ecb_node(raw, channel, 0x05) as node:
        name = "conformance/forged/latest"
        uid = name_to_uid(name)
        await raw_bind(raw, Request(PUB_BIND, 0x05, uid), 0x0124, node.publish(name, b"\x01"))
        since = raw.mark()
        declaring = asyncio.create_task(node.declare(name, period_ms=10, deadline_ms=10))
        await raw.expect(Declare, since=since)
        answered = raw.send(Grant(0x0124, 0x05, 0x02), Refuse(0x0124, 0x05, 0x05, 0x0124, 900))
        with pytest.raises(Unschedulable):
            await asyncio.wait_for(declaring, 5.0)
        assert not raw.find(Declare, since=answered)
        raw.send(Grant(0x0124, 0x05, 0x03))
        await handled(raw, 0x05)
        since = raw.mark()
        await node.publish(name, b"\x02")
        await raw.expect(Event(0x80, 0x05, 0x0124, b"\x02"), since=since)


async def test_node_follows_the_latest_verdict_of_a_declared_stream(
    raw: Wire, channel: str
) -> None:
    async with raw_ecb_node(raw, channel, 0x05) as node:
        name = "conformance/forged/follows"
        uid = name_to_uid(name)
        await raw_bind(raw, Request(PUB_BIND, 0x05, uid), 0x0125, node.publish(name, b"\x01"))
        since = raw.mark()
        declaring = asyncio.create_task(node.declare(name, period_ms=10, deadline_ms=10))
        await raw.expect(Declare, since=since)
        raw.send(Refuse(0x0125, 0x05, 0x05, 0x0125, 900), Grant(0x0125, 0x05, 0x02))
        assert await asyncio.wait_for(declaring, 5.0) == 0x02  # the latest: the Grant
        raw.send(Grant(0x0125, 0x05, 0x07))  # unasked: another declaration moved it
        await sent_at(raw, node, name, 0x0125, 0x07)
        raw.send(Refuse(0x0125, 0x05, 0x05, 0x0125, UNBOUNDED))  # not admitted: best effort
        await sent_at(raw, node, name, 0x0125, 0x80)
        raw.send(Grant(0x0125, 0x05, 0x02))  # admitted again
        await sent_at(raw, node, name, 0x0125, 0x02)


# --- our node: refusals ---------------------------------------------------------------------


async def _census(raw: Wire) -> int:
    """Answer our node's Knock with a Census; wait for its sixteen Stage frames."""
    await raw.expect(Knock, timeout=3.0)
    since = raw.send(Census(0))
    for s, n in enumerate(nibbles(NODE_ID)):
        await raw.expect(Stage(0, s, n), since=since)
    return raw.mark()


async def test_a_joiner_takes_no_refusal_that_an_offer_or_assign_contradicts(
    raw: Wire, channel: str
) -> None:
    node = Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=10)
    starting = asyncio.create_task(node.start())
    try:
        await _census(raw)
        since = raw.send(TxNodesFull(NODE_ID), Offer(0x05, NODE_ID))
        await raw.expect(Request(CLAIM, 0x05, NODE_ID), since=since)
        raw.send(Failed(NODE_ID), Assign(0x05, NODE_ID))
        await asyncio.wait_for(starting, 5.0)
        assert node.stats()["txnode"] == 0x05
    finally:
        starting.cancel()
        await node.close()


@pytest.mark.parametrize("refusal", ["TxNodesFull", "Failed"])
async def test_a_refusal_that_stands_ends_the_join_and_the_joiner_does_not_knock_meanwhile(
    raw: Wire, channel: str, refusal: str
) -> None:
    node = Node(can=f"virtual:{channel}", node_id=NODE_ID, join_timeout=20)
    starting = asyncio.create_task(node.start())
    try:
        await _census(raw)
        frame: Frame = TxNodesFull(NODE_ID) if refusal == "TxNodesFull" else Failed(NODE_ID)
        refused = raw.send(frame)
        error = Exhausted if refusal == "TxNodesFull" else BrokerUnavailable
        with pytest.raises(error):
            await asyncio.wait_for(starting, 10.0)
        ended = asyncio.get_running_loop().time()
        assert ended - raw.log[refused].at >= REFUSAL_WAIT - 0.05  # not before it stood
        assert not raw.find(Knock, since=refused)
    finally:
        starting.cancel()
        await node.close()


async def test_a_binding_refusal_is_void_once_the_request_is_answered(
    raw: Wire, channel: str
) -> None:
    async with raw_ecb_node(raw, channel, 0x05) as node:
        name = "conformance/forged/bind"
        uid = name_to_uid(name)
        since = raw.mark()
        subscribing = asyncio.create_task(node.subscribe(name))
        asked, _ = await raw.expect(Request(SUB_BIND, 0x05, uid), since=since)
        refused = raw.send(EtagsFull(uid), Limit(0x05, uid), Failed(uid))
        await raw.expect(Request(SUB_BIND, 0x05, uid), since=refused)  # it asks again
        raw.send(Bind(0x0126, uid))
        await asyncio.wait_for(subscribing, 5.0)
        assert asked < refused


async def test_a_binding_refusal_that_stands_ends_the_request(raw: Wire, channel: str) -> None:
    async with raw_ecb_node(raw, channel, 0x05) as node:
        name = "conformance/forged/limit"
        uid = name_to_uid(name)

        def refuse(frame: Frame) -> None:
            if frame == Request(SUB_BIND, 0x05, uid):
                raw.send(Limit(0x05, uid))

        raw.handlers.append(refuse)
        since = raw.mark()
        with pytest.raises(Exhausted):
            await node.subscribe(name)
        assert len(raw.find(Request(SUB_BIND, 0x05, uid), since)) >= 2  # asked on meanwhile


# --- our CAN-ECB: corrections -----------------------------------------------------------------


async def _publisher(raw: Wire, node_id: int, name: str) -> tuple[RawNode, int]:
    node = RawNode(raw, node_id)
    await node.join()
    bind = await node.ask(PUB_BIND, name_to_uid(name))
    return node, bind.etag


async def test_ecb_answers_a_grant_of_a_stream_it_did_not_admit_with_a_refuse(
    raw: Wire, can_ecb: CanEcb
) -> None:
    node, etag = await _publisher(raw, 0xF01, "conformance/forged/ecb/grant")
    assert node.txnode is not None
    since = raw.send(Grant(etag, node.txnode, 0x02))
    await raw.expect(Refuse(etag, node.txnode, node.txnode, etag, UNBOUNDED), since=since)
    since = raw.send(Refuse(etag, node.txnode, node.txnode, etag, 1))  # contradicts nothing
    await raw.expect_none((Grant, Refuse), since=since + 1, window=0.3)


async def test_ecb_answers_verdicts_that_contradict_its_grant_with_its_grant(
    raw: Wire, can_ecb: CanEcb
) -> None:
    node, etag = await _publisher(raw, 0xF02, "conformance/forged/ecb/admitted")
    t = node.txnode
    assert t is not None
    since = raw.send(Declare(t, etag, 1, 100, 100, 0))
    _, grant = await raw.expect(lambda f: isinstance(f, Grant) and f.etag == etag, since=since)
    for forged in (Grant(etag, t, grant.priority + 5), Refuse(etag, t, t, etag, UNBOUNDED)):
        since = raw.send(forged)
        await raw.expect(grant, since=since + 1)


@pytest.mark.parametrize("refusal", ["TxNodesFull", "Failed"])
async def test_ecb_answers_a_refusal_of_an_assigned_node_with_its_assign(
    raw: Wire, can_ecb: CanEcb, refusal: str
) -> None:
    node = RawNode(raw, 0xF03)
    t = await node.join()
    since = raw.send(TxNodesFull(0xF03) if refusal == "TxNodesFull" else Failed(0xF03))
    await raw.expect(Assign(t, 0xF03), since=since + 1)


async def test_ecb_refuses_bindings_past_a_node_ids_quota_and_binds_what_exists(
    raw: Wire, can_ecb: CanEcb
) -> None:
    rogue, other = RawNode(raw, 0xF04), RawNode(raw, 0xF05)
    t = await rogue.join()
    await other.join()
    existing = await other.ask(SUB_BIND, 0xE415_0000)
    uids = [0xC0_0000 + i for i in range(QUOTA)]
    since = raw.send(*(Request(SUB_BIND, t, u) for u in uids))
    await raw.expect(lambda f: isinstance(f, Bind) and f.uid == uids[-1], since=since, timeout=30)
    since = raw.send(Request(SUB_BIND, t, 0xC0_FFFF))
    await raw.expect(Limit(t, 0xC0_FFFF), since=since)
    assert (await rogue.ask(SUB_BIND, existing.uid)).etag == existing.etag  # costs nothing
