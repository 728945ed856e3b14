"""Issue 32, CAN: what a forger on the bus could do, and the bound on it now. In one process, on
python-can virtual buses, with real nodes and the real CAN-ECB; the forger has a link of its own
and answers what it hears, as an attacker's program on the bus would.

- a Grant nobody asked for (a channel with no declaration) changes nothing; a forged verdict on a
  declared stream lasts until the CAN-ECB's correction, which follows at once; a forged verdict
  racing the CAN-ECB's answer does not become the node's answer;
- a TxNodesFull or Failed forged during a join ends no join the CAN-ECB serves;
- two rogue node ids cannot take the bus's etags: each may create ``QUOTA`` bindings per size
  class; a node using hundreds of channels is never refused.

(The lost-database attack needs a daemon that stops: tests/test_can_durable_processes.py.)
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path

import can
import pytest

from ups import BrokerUnavailable, Exhausted, Node, Unschedulable, name_to_uid
from ups import _canproto as p
from ups._canface import CanFace
from ups._canlink import CanLink
from ups._errors import DecodeError
from ups.broker.can_ecb import CanEcb

from .conftest import HeldBus, eventually, handled, running_ecb
from .conftest import joined_nodes as nodes
from .conftest import send_management as send

#: bindings one node id may create in size class 0 (docs/protocol.md, Bounds)
QUOTA = 1024


class Forger:
    """A program on the bus with a link of its own: ``react(frame)`` returns the frames it sends
    in answer to each management frame it hears (at once, from the loop that reads them)."""

    def __init__(self, bus: str, react: Callable[[p.Management], list[p.Management]]) -> None:
        self.link = CanLink.open(bus)
        self.react = react
        self.sent: list[p.Management] = []
        self.link.add_handler(self._on_frame, None)
        self.link.start()

    def _on_frame(self, frame: can.Message) -> None:
        if not frame.is_extended_id or not p.is_management(frame.arbitration_id):
            return
        try:
            msg = p.decode(frame.arbitration_id, bytes(frame.data))
        except DecodeError:
            return
        for forged in self.react(msg):
            can_id, data = p.encode(forged)
            self.link.send(can_id, data)
            self.sent.append(forged)

    def close(self) -> None:
        self.link.close()


@asynccontextmanager
async def forging(
    bus: str, react: Callable[[p.Management], list[p.Management]]
) -> AsyncIterator[Forger]:
    forger = Forger(bus, react)
    try:
        yield forger
    finally:
        forger.close()


def can_face(node: Node) -> CanFace:
    face = node.face
    assert isinstance(face, CanFace)
    return face


async def priority_on_the_wire(pub: Node, sub: Node, channel: str) -> int:
    subscription = await sub.subscribe(channel)
    await pub.publish(channel, b"\x01")
    msg = await subscription.get_msg(timeout=5)
    await subscription.close()
    return msg.priority


# --- Grant and Refuse ---------------------------------------------------------------------------


async def test_a_grant_for_a_channel_nobody_declared_changes_nothing(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    """The attack: Grant(etag of x, the publisher's TxNode, 0x02) raised x from 0x80 to 0x02 for
    good (the node took any Grant naming its TxNode and an etag it relies on)."""
    async with nodes(bus, [1, 2]) as (pub, sub):
        assert await priority_on_the_wire(pub, sub, "x") == p.DEFAULT_PRIORITY
        etag, txnode = ecb.etags[name_to_uid("x")], pub.stats()["txnode"]
        send(raw_bus, p.Grant(etag, txnode, 0x02))
        await handled(pub, raw_bus)
        assert await priority_on_the_wire(pub, sub, "x") == p.DEFAULT_PRIORITY
        assert pub.stats()["stray_verdicts"] >= 1  # (and the CAN-ECB's Refuse, ignored too)
        # the CAN-ECB heard a Grant it did not send for a stream it never admitted: it said so
        await eventually(lambda: ecb.counters["conflicts"] >= 1)


async def test_a_forged_grant_on_a_declared_stream_lasts_until_the_correction(
    bus: str, ecb: CanEcb, raw_bus: can.BusABC
) -> None:
    """Another priority for an admitted stream: the node follows the latest verdict for its
    stream, and the CAN-ECB, hearing a Grant that contradicts its own, sends its own again."""
    async with nodes(bus, [1, 2]) as (pub, sub):
        granted = await pub.declare("rt", period_ms=10, deadline_ms=10, size_bytes=1)
        etag, txnode = ecb.etags[name_to_uid("rt")], pub.stats()["txnode"]
        send(raw_bus, p.Grant(etag, txnode, 0x70))
        await eventually(lambda: ecb.counters["conflicts"] >= 1)
        await handled(pub, raw_bus)  # the correction came before this barrier's Bind
        assert await priority_on_the_wire(pub, sub, "rt") == granted
        send(raw_bus, p.Refuse(etag, txnode, etag, txnode, 0xFFFF))  # demoted, then re-granted
        await eventually(lambda: ecb.counters["conflicts"] >= 2)
        await handled(pub, raw_bus)
        assert await priority_on_the_wire(pub, sub, "rt") == granted


@asynccontextmanager
async def held_ecb(bus: str, db: Path, **options: float) -> AsyncIterator[tuple[CanEcb, HeldBus]]:
    """A CAN-ECB whose receiving can be held (a busy one): a forger can answer first."""
    held = HeldBus(bus.partition(":")[2])
    link = CanLink(held)
    ecb = CanEcb(link, db, recovery=0.1, **options)  # type: ignore[arg-type]
    try:
        await ecb.start()
        await eventually(lambda: not ecb.recovering)
        yield ecb, held
    finally:
        held.reading.set()
        ecb.close()
        link.close()


@pytest.mark.parametrize("verdict", ["Refuse", "Grant"])
async def test_a_verdict_forged_before_the_can_ecbs_answer_is_not_the_answer(
    bus: str, tmp_path: Path, verdict: str
) -> None:
    """The forger answers the DECLARE before the CAN-ECB does: a Refuse of a stream the CAN-ECB
    admits, or a Grant of one it refuses (a deadline no bus can meet)."""
    deadline = 10.0 if verdict == "Refuse" else 0.1
    async with (
        held_ecb(bus, tmp_path / "ecb.db", bitrate=125_000) as (ecb, held),
        nodes(bus, [1]) as (pub,),
    ):
        await pub.publish("rt", b"\x00")
        etag, txnode = ecb.etags[name_to_uid("rt")], pub.stats()["txnode"]
        forged = asyncio.Event()

        def react(msg: p.Management) -> list[p.Management]:
            if not isinstance(msg, p.Declare):
                return []
            forged.set()
            if verdict == "Refuse":
                return [p.Refuse(etag, txnode, etag, txnode, 0xFFFF)]
            return [p.Grant(etag, txnode, 0x02)]

        async with forging(bus, react):
            await held.hold()  # the CAN-ECB is busy: the forger answers first
            declaring = asyncio.create_task(
                pub.declare("rt", period_ms=10, deadline_ms=deadline, size_bytes=1)
            )
            await forged.wait()
            held.reading.set()
            if verdict == "Refuse":
                assert await declaring == ecb.granted[(etag, txnode)]
            else:
                with pytest.raises(Unschedulable):
                    await declaring
                assert await priority_on_the_wire(pub, pub, "rt") == p.DEFAULT_PRIORITY


# --- a forged answer to a re-binding ------------------------------------------------------------


async def test_a_forged_answer_to_a_rebinding_that_the_can_ecb_corrects_at_once_is_not_adopted(
    bus: str, tmp_path: Path, raw_bus: can.BusABC
) -> None:
    """The settle rule (docs/protocol.md, "A Bind counts as the answer"; ``Bindings._spoil``).
    A subscriber re-binding x after a contradiction hears a forged answer Bind(F, x) and, at
    once after it, the CAN-ECB's correction Bind(E, x): it must rely on E, where x's
    publisher sends. Without the rule it adopted F 50 ms later, ignoring the true Bind, and
    listened on an etag nobody publishes on, for good (mutation audit, issue 41).

    The order is made, not hoped for: the CAN-ECB is held (a busy one) from before the
    contradiction until the forged answer is on the bus, and the subscriber is held while the
    forged answer and the CAN-ECB's Binds queue up for it, so it handles them back to back.
    The publisher is held throughout (it is busy: it has not read the contradiction yet, so
    it still sends on E, as a publisher that never heard the forger would)."""
    uid, forged = name_to_uid("x"), 0x123  # an etag nothing on the bus is bound to
    channel = bus.partition(":")[2]
    held_pub, held_sub = HeldBus(channel), HeldBus(channel)
    link_pub, link_sub = CanLink(held_pub), CanLink(held_sub)
    try:
        async with (
            held_ecb(bus, tmp_path / "ecb.db") as (ecb, held),
            Node(can=link_pub, node_id=1, join_timeout=15) as pub,
            Node(can=link_sub, node_id=2, join_timeout=15) as sub_node,
        ):
            sub = await sub_node.subscribe("x")
            await pub.publish("x", b"before")
            assert (await sub.get_msg(timeout=5)).data == b"before"
            etag = ecb.etags[uid]
            assert forged != etag and forged not in ecb.etags.values()
            face = can_face(sub_node)
            await held_pub.hold()  # the publisher reads nothing more until the end
            await held.hold()  # nor does the CAN-ECB, for now
            send(raw_bus, p.Bind(etag, 0xBAD))  # contradicts x: the subscriber binds it again
            await eventually(lambda: uid in face.bindings.pending)
            await held_sub.hold()
            conflicts = ecb.counters["conflicts"]
            send(raw_bus, p.Bind(forged, uid))  # the forged answer
            held.reading.set()  # the CAN-ECB corrects both forged Binds and answers the requests
            await eventually(lambda: ecb.counters["conflicts"] >= conflicts + 2)
            held_sub.reading.set()  # the forged answer, then the true Binds, back to back
            await eventually(lambda: uid in face.bindings.bound)
            await pub.publish("x", b"after")  # on E: the publisher never heard the forger
            try:
                assert (await sub.get_msg(timeout=5)).data == b"after"
            except TimeoutError:
                raise AssertionError(
                    f"the subscriber relies on etag {face.bindings.bound.get(uid, -1):#x} for x, "
                    f"which is at {etag:#x}"
                ) from None
    finally:
        held_pub.reading.set()
        held_sub.reading.set()
        link_pub.close()
        link_sub.close()


# --- TxNodesFull and Failed during a join ---------------------------------------------------------


JOINERS = [0x0A11_0001, 0x0A11_0002, 0x0A11_0003]


def refusals(kind: str, when: str) -> Callable[[p.Management], list[p.Management]]:
    """A forger that says TxNodesFull(id) or Failed(id) to each joiner: when the CAN-ECB offers
    it a TxNode (the joiner claims, and the CAN-ECB stores the assignment), or as soon as a
    census starts (it knows the ids: they are stable)."""
    make: Callable[[int], p.Management] = p.TxNodesFull if kind == "TxNodesFull" else p.Failed

    def react(msg: p.Management) -> list[p.Management]:
        if when == "offer" and isinstance(msg, p.Offer) and msg.node_id in JOINERS:
            return [make(msg.node_id)]
        if when == "census" and isinstance(msg, p.Census):
            return [make(i) for i in JOINERS]
        return []

    return react


@pytest.mark.parametrize(
    ("kind", "when"), [("TxNodesFull", "offer"), ("TxNodesFull", "census"), ("Failed", "offer")]
)
async def test_a_refusal_forged_during_a_join_ends_no_join(
    bus: str, ecb: CanEcb, kind: str, when: str
) -> None:
    """The attack: three joiners, each told "all 127 TxNodes are taken" while the CAN-ECB
    assigned them: 3 of 3 failed."""
    await eventually(lambda: not ecb.recovering)
    async with forging(bus, refusals(kind, when)) as forger:
        joiners = [Node(can=bus, node_id=i, join_timeout=15) for i in JOINERS]
        try:
            results = await asyncio.gather(*(n.start() for n in joiners), return_exceptions=True)
            failed = [r for r in results if isinstance(r, Exhausted | BrokerUnavailable)]
            assert not failed, f"{len(failed)} of 3 joins failed: {failed}"
            assert {n.node_id: n.stats()["txnode"] for n in joiners} == ecb.txnodes
        finally:
            for node in joiners:
                await node.close()
        assert forger.sent, "the forger never struck"


@pytest.mark.parametrize("kind", ["EtagsFull", "Failed", "Limit"])
async def test_a_refusal_forged_while_a_node_binds_ends_no_request(
    bus: str, ecb: CanEcb, kind: str
) -> None:
    """The same for a binding: each SUB_BIND answered at once by a forged refusal."""

    def react(msg: p.Management) -> list[p.Management]:
        if not isinstance(msg, p.Request) or msg.kind != p.SUB_BIND:
            return []
        if kind == "Limit":
            return [p.Limit(msg.txnode, msg.value)]
        return [p.EtagsFull(msg.value) if kind == "EtagsFull" else p.Failed(msg.value)]

    async with nodes(bus, [1]) as (node,), forging(bus, react) as forger:
        await node.subscribe(*[f"bound/{i}" for i in range(20)])
        assert node.stats()["bindings"] == 20 and len(forger.sent) >= 20
        # each refusal is counted: while the request waits, or as stray once it was answered
        # (the CAN-ECB's Bind may come first; the last refusal may come after subscribe)
        await eventually(lambda: sum(node.stats()[k] for k in ("refusals", "stray_refusals")) >= 20)


# --- the binding quota --------------------------------------------------------------------------


async def test_a_rogue_pair_of_ids_cannot_take_the_buss_etags(
    bus: str, tmp_path: Path, raw_bus: can.BusABC
) -> None:
    """The attack: two node ids sent 16,400 PUB_BINDs of made-up channels and took all 12,272
    etags of size class 0. Now each may create ``QUOTA``; a node that uses 300 new channels
    afterwards gets them all."""
    async with (
        running_ecb(bus, tmp_path / "ecb.db", recovery=0.1) as ecb,
        nodes(bus, [0xBAD1, 0xBAD2]) as rogues,
    ):
        await eventually(lambda: not ecb.recovering)
        before = ecb.counters["requests"]
        for rogue in rogues:
            txnode = rogue.stats()["txnode"]
            for i in range(8200):
                send(raw_bus, p.Request(p.PUB_BIND, txnode, (0xBAD0 + txnode) << 32 | i))
        await eventually(lambda: ecb.counters["requests"] >= before + 16_400, timeout=60)
        await eventually(lambda: not ecb._etags._pending, timeout=60)  # the writes are done
        taken = len(ecb.etags)
        assert taken <= 2 * QUOTA, f"the rogue pair took {taken} etags"
        assert ecb.counters["quota_hit"] >= 16_400 - 2 * QUOTA
        async with Node(can=bus, node_id=0x600D, join_timeout=15) as good:
            await good.subscribe(*[f"robot/{i}" for i in range(300)])
            assert good.stats()["bindings"] == 300
