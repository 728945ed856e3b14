"""libups-ecb's join half (c/ups_ecb_join.c) and its dispatcher (c/ups_ecb.c): censuses of many
joiners at once, docs/protocol.md's worked example frame by frame, lapsed Offers and late
claims, TxNodesFull and the lease, and restarts with the blob (kept, or corrupt and refused).

The compiled library serves a python-can virtual bus (``broker/c_ecb.py``'s CEcb) against
nodes written from the document (``tests/conformance/_wire``'s RawNode) or frames the test
sends itself. A full node table and the lease are driven call by call with the time given
explicitly (``Driver``), also in a child process under AddressSanitizer with the small tables
of the asan build (6 nodes)."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from tests import cecb_calls as calls
from tests.conformance._frames import (
    PUB_BIND,
    SUB_BIND,
    UNSUB,
    Assign,
    Bind,
    Census,
    Event,
    Failed,
    Hello,
    Knock,
    Offer,
    Query,
    Request,
    Serving,
    Stage,
    TxNodesFull,
    claim,
    encode,
    nibbles,
)
from tests.conformance._wire import RawNode, Wire
from tests.procs import sanitizer_env
from ups._canlink import CanLink
from ups._cnode import build
from ups.broker._cecb_lib import SOURCES, VARIANTS
from ups.broker.c_ecb import CEcb

ROOT = Path(__file__).resolve().parent.parent
SPEED = 0xBBCCB9C002D5ED59  #: the worked example's channel UID


@asynccontextmanager
async def c_ecb(channel: str, state: Path, **options: Any) -> AsyncIterator[CEcb]:
    link = CanLink.open(f"virtual:{channel}")
    try:
        ecb = CEcb(link, state, **{"recovery": 0.2, **options})
        await ecb.start()
        try:
            yield ecb
        finally:
            ecb.close()
    finally:
        link.close()


@pytest.fixture
async def wire(request: pytest.FixtureRequest) -> AsyncIterator[Wire]:
    w = Wire(f"cecb-join-{request.node.name}-{id(request)}")
    yield w
    await w.close()


async def until(check: Any, what: str, timeout: float = 10.0) -> None:
    """Poll ``check()`` until it holds (an event of the CAN-ECB's, seen in its counters)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not check():
        assert loop.time() < deadline, f"not within {timeout} s: {what}"
        await asyncio.sleep(0.005)


async def served(wire: Wire) -> None:
    """Wait until the CAN-ECB's first recovery window is over (its Serving follows it)."""
    await wire.expect(Serving, timeout=5.0)


# --- censuses on the bus ----------------------------------------------------------------------


def shared_prefix_ids(count: int) -> list[int]:
    """``count`` ids sharing their first 12 nibbles, branching at several later stages."""
    base = 0x0123456789AB0000
    return [base | (k * 0x0111 + (k % 3) * 0x1000) & 0xFFFF for k in range(1, count + 1)]


@pytest.mark.parametrize("count", [1, 3, 20])
async def test_joiners_at_once_with_long_shared_prefixes(
    wire: Wire, tmp_path: Path, count: int
) -> None:
    ids = shared_prefix_ids(count)
    assert len(set(ids)) == count
    async with c_ecb(wire.channel, tmp_path / "ecb.blob") as ecb:
        await served(wire)
        nodes = [RawNode(wire, i) for i in ids]
        txnodes = await asyncio.gather(*(n.join() for n in nodes))
        assert len(set(txnodes)) == count
        assert ecb.txnodes == dict(zip(ids, txnodes, strict=True))
        stats = ecb.stats()
        assert stats["joined"] == count
        assert stats["census_cut"] == 0
        if count > 1:  # they share 12 nibbles: the census branched into queries
            assert wire.find(Query)


# --- the worked example of docs/protocol.md -----------------------------------------------------


def hexed(frame: Any) -> tuple[str, str]:
    can_id, data = encode(frame)
    return f"{can_id:08X}", data.hex(" ")


async def test_the_worked_example_frame_by_frame(wire: Wire, tmp_path: Path) -> None:
    """The tables of *Worked example*: the identifiers and data the document gives are those
    this CAN-ECB sends (0x9B holds TxNode 1 from the start: it claims it in the recovery
    window, so that the joiners get TxNodes 0, 2 and 3 as in the document)."""
    async with c_ecb(wire.channel, tmp_path / "ecb.blob", recovery=1.0):
        _, hello = await wire.expect(Hello)
        assert hexed(hello)[0] == "001FF300"
        wire.send(claim(1, 0x9B))  # adopted in the recovery window
        await served(wire)

        since = wire.send(Knock())
        _, census = await wire.expect(Census, since=since)
        assert hexed(census) == ("001FF000", "")
        since = wire.send(*(Stage(0, s, n) for s, n in enumerate(nibbles(0x5B))))
        _, offer = await wire.expect(Offer, since=since)
        assert hexed(offer) == ("001FE080", "00 00 00 00 00 00 00 5b")
        since = wire.send(claim(0, 0x5B))
        _, assign = await wire.expect(Assign, since=since)
        assert hexed(assign) == ("001FE000", "00 00 00 00 00 00 00 5b")

        since = wire.send(Request(SUB_BIND, 0, SPEED))
        _, bind = await wire.expect(Bind, since=since)
        assert hexed(bind) == ("003FC010", "bb cc b9 c0 02 d5 ed 59")
        since = wire.send(Request(PUB_BIND, 1, SPEED))
        _, bind = await wire.expect(Bind, since=since)
        assert hexed(bind) == ("003FC010", "bb cc b9 c0 02 d5 ed 59")
        wire.send(Event(0x20, 1, 0x10, b"\x01\x02"), Request(UNSUB, 0, SPEED))

        # two nodes, 0x25 and 0x3A, power up together: identical stages 0-13 once each
        since = wire.send(Knock())
        _, census = await wire.expect(Census, since=since)
        assert hexed(census) == ("001FF001", "")
        frames = [Stage(1, s, 0) for s in range(14)]
        frames += [Stage(1, 14, 2), Stage(1, 14, 3), Stage(1, 15, 5), Stage(1, 15, 10)]
        since = wire.send(*frames)
        _, q2 = await wire.expect(Query, since=since)
        _, q3 = await wire.expect(lambda f: isinstance(f, Query) and f != q2, since=since)
        assert (hexed(q2), hexed(q3)) == (
            ("001FD2E2", "00 00 00 00 00 00 00 20"),
            ("001FD3E3", "00 00 00 00 00 00 00 30"),
        )
        since = wire.send(Stage(2, 15, 5), Stage(3, 15, 10))
        _, o2 = await wire.expect(Offer, since=since)
        _, o3 = await wire.expect(lambda f: isinstance(f, Offer) and f != o2, since=since)
        assert (hexed(o2), hexed(o3)) == (
            ("001FE082", "00 00 00 00 00 00 00 25"),
            ("001FE083", "00 00 00 00 00 00 00 3a"),
        )
        since = wire.send(claim(2, 0x25), claim(3, 0x3A))
        _, a2 = await wire.expect(Assign, since=since)
        _, a3 = await wire.expect(lambda f: isinstance(f, Assign) and f != a2, since=since)
        assert (hexed(a2), hexed(a3)) == (
            ("001FE002", "00 00 00 00 00 00 00 25"),
            ("001FE003", "00 00 00 00 00 00 00 3a"),
        )


# --- Offers that lapse --------------------------------------------------------------------------


async def test_a_lapsed_offer_is_kept_for_a_late_claim(wire: Wire, tmp_path: Path) -> None:
    async with c_ecb(wire.channel, tmp_path / "ecb.blob") as ecb:
        await served(wire)
        slow = RawNode(wire, 0x51)
        slow.claim_offers = False
        since = wire.send(Knock())
        _, offer = await wire.expect(lambda f: isinstance(f, Offer) and f.node_id == 0x51,
                                     since=since)  # fmt: skip
        slow.close()  # it answers no census from now on (else it is offered the same again)
        await until(lambda: ecb.stats()["offers_withdrawn"] >= 1, "the Offer lapses")
        # another joiner does not get the lapsed Offer's TxNode while others are free
        other = RawNode(wire, 0x52)
        assert await other.join() != offer.txnode
        # the slow node's late claim still gets it
        since = wire.send(claim(offer.txnode, 0x51))
        await wire.expect(Assign(offer.txnode, 0x51), since=since)
        assert ecb.stats()["late_claims"] == 1
        assert ecb.txnodes[0x51] == offer.txnode
        other.close()


# --- restarts and the blob ------------------------------------------------------------------------


async def test_a_restart_with_the_blob_keeps_every_txnode(wire: Wire, tmp_path: Path) -> None:
    state = tmp_path / "ecb.blob"
    ids = shared_prefix_ids(3)
    async with c_ecb(wire.channel, state) as ecb:
        await served(wire)
        nodes = [RawNode(wire, i) for i in ids]
        await asyncio.gather(*(n.join() for n in nodes))
        before = ecb.txnodes
    for node in nodes:
        node.answer_hello = False  # the table alone brings them back
    async with c_ecb(wire.channel, state) as ecb:
        assert ecb.restored
        assert ecb.txnodes == before
        await served(wire)
        late = RawNode(wire, 0x77)  # a new joiner gets a TxNode nobody holds
        assert await late.join() not in before.values()
        assert ecb.stats()["blob_refused"] == 0


async def test_a_corrupt_blob_is_refused_and_the_nodes_claim_again(
    wire: Wire, tmp_path: Path
) -> None:
    state = tmp_path / "ecb.blob"
    ids = shared_prefix_ids(3)
    async with c_ecb(wire.channel, state) as ecb:
        await served(wire)
        nodes = [RawNode(wire, i) for i in ids]
        await asyncio.gather(*(n.join() for n in nodes))
        before = ecb.txnodes
    blob = bytearray(state.read_bytes())
    blob[len(blob) // 2] ^= 0x40  # one bit flipped: the CRC no longer holds
    state.write_bytes(bytes(blob))
    async with c_ecb(wire.channel, state, recovery=1.0) as ecb:
        assert not ecb.restored
        assert ecb.stats()["blob_refused"] == 1
        # the nodes answer the Hello with CLAIM, adopted in the recovery window
        await until(lambda: ecb.txnodes == before, "the claims are adopted")
        assert ecb.stats()["adopted"] == len(ids)


# --- call by call: a full table, the lease, the blob, a clock that wraps --------------------------


class Driver(calls.Driver):
    """The call-by-call driver (tests/cecb_calls.py), with a joiner's census."""

    def census(self, node_id: int) -> list[Any]:
        """A Knock, the Stages of ``node_id`` for the Census, and the time to read them."""
        out = self.rx(Knock())
        census = [f for f in out if isinstance(f, Census)]
        assert census, out
        stages = [Stage(census[0].epoch, s, n) for s, n in enumerate(nibbles(node_id))]
        return out + self.rx(*stages) + self.tick(300)


def scenario_full_table(variant: str) -> None:
    """Fill the node table (claims adopted at start, then joins by census); TxNodesFull
    (nodes_full) until the lease has passed for a TxNode silent longest, which is then
    reclaimed and offered; the clock wraps meanwhile; the blob brings the table back, a
    corrupt one is refused."""
    ecb = Driver(variant, lease_s=2, recovery_ms=300)
    n = ecb.config["nodes"]
    ecb.start(0xFFFFF000)  # the clock wraps in 4 s
    adopted = n // 2
    assert ecb.rx(*(claim(t, 0xA000 + t) for t in range(adopted))) == []
    ecb.tick(400)
    for k in range(adopted, n):
        out = ecb.census(0xB000 + k)
        offers = [f for f in out if isinstance(f, Offer)]
        assert offers == [Offer(offers[0].txnode, 0xB000 + k)], out
        assert ecb.rx(claim(offers[0].txnode, 0xB000 + k)) == [Assign(offers[0].txnode,
                                                                      0xB000 + k)]  # fmt: skip
        ecb.rx(*(Event(0x80, t, 0x10, b"") for t in ecb.nodes().values()))  # all in use
    table = ecb.nodes()
    assert len(table) == n and len(set(table.values())) == n
    out = ecb.census(0xCCCC)
    assert TxNodesFull(0xCCCC) in out
    assert ecb.counters()["nodes_full"] == 1
    # every node but the first adopted one speaks; past the lease its TxNode is reclaimed
    quiet = table[0xA000]
    for _ in range(3):
        ecb.tick(900)
        ecb.rx(*(Event(0x80, t, 0x10, b"") for t in table.values() if t != quiet))
    out = ecb.census(0xCCCC)
    assert Offer(quiet, 0xCCCC) in out, out
    assert ecb.counters()["reclaimed"] == 1
    assert ecb.rx(claim(quiet, 0xCCCC)) == [Assign(quiet, 0xCCCC)]
    table = ecb.nodes()
    assert table[0xCCCC] == quiet and 0xA000 not in table
    # the blob: the same table in another CAN-ECB; one flipped bit, and it is refused
    blob = ecb.save()
    other = Driver(variant)
    assert other.c.ups_ecb_restore(other.state, blob, len(blob)) == 0
    assert other.nodes() == table
    for bad in (blob[:-1], blob[:5] + bytes([blob[5] ^ 1]) + blob[6:], blob + b"\0"):
        third = Driver(variant)
        assert third.c.ups_ecb_restore(third.state, bad, len(bad)) < 0
        assert third.nodes() == {} and third.counters()["blob_refused"] == 1


def test_incomplete_answers_are_asked_again_and_late_ones_reopen_their_query() -> None:
    ecb = Driver("full", recovery_ms=100)
    ecb.start(0xFFFFFF00)
    ecb.tick(200)
    x, y = 0x0123456789ABCDEF, 0x0FEDCBA987654321
    # stage 9 of x is lost: the prefix certain (stages 0-8) is queried again
    (census,) = [f for f in ecb.rx(Knock()) if isinstance(f, Census)]
    ecb.rx(*(Stage(census.epoch, s, n) for s, n in enumerate(nibbles(x)) if s != 9))
    (query,) = [f for f in ecb.tick(300) if isinstance(f, Query)]
    assert query.prefix == nibbles(x, 9)
    counters = ecb.counters()
    assert (counters["census_incomplete"], counters["census_retries"]) == (1, 1)
    ecb.rx(*(Stage(query.epoch, s, n) for s, n in enumerate(nibbles(x)) if s >= 9))
    # the retry closed unanswered before them: reopened, and the slack makes it wait longer
    assert [f for f in ecb.tick(1000) if isinstance(f, Offer)] == [Offer(0, x)]
    assert ecb.counters()["census_reopened"] == 1
    # a census nobody answered in time is reopened by its late answers
    (census,) = [f for f in ecb.rx(Knock()) if isinstance(f, Census)]
    assert [f for f in ecb.tick(3000) if not isinstance(f, Serving)] == []
    ecb.rx(*(Stage(census.epoch, s, n) for s, n in enumerate(nibbles(y))))
    assert [f for f in ecb.tick(5000) if isinstance(f, Offer)] == [Offer(1, y)]  # slack 4 s
    assert ecb.counters()["census_reopened"] == 2


def test_claims_moves_and_the_corrections_of_forged_join_frames() -> None:
    """A claim of another's TxNode in the recovery window moves the claimer (Assign of a free
    one); after it, a forged Assign, TxNodesFull or Failed of a node id the table gives a
    TxNode is answered with the table's Assign, of one offered a TxNode with the Offer again;
    an Offer of another CAN-ECB is no correction; a CLAIM outside a recovery window by a node
    the table gives another free TxNode is answered with the table's Assign."""
    a, b, c = 0xAAA, 0xBBB, 0xCCC

    def corrections(out: list[Any]) -> list[Any]:  # a serving one also answers with Serving
        return [f for f in out if not isinstance(f, Serving)]

    ecb = Driver("full", recovery_ms=200)
    ecb.start(0)
    assert ecb.rx(claim(1, a)) == []  # adopted
    assert ecb.rx(claim(1, b)) == [Assign(0, b)]  # TxNode 1 is a's: b moves to a free one
    ecb.tick(300)
    assert ecb.nodes() == {a: 1, b: 0}
    assert corrections(ecb.rx(Assign(5, a))) == [Assign(1, a)]
    assert corrections(ecb.rx(TxNodesFull(b))) == [Assign(0, b)]
    assert corrections(ecb.rx(Failed(a))) == [Assign(1, a)]
    assert corrections(ecb.rx(Offer(7, a))) == []
    assert ecb.rx(claim(9, a)) == [Assign(1, a)]  # told to move by a forged Assign: back
    out = ecb.census(c)
    assert Offer(2, c) in out
    assert corrections(ecb.rx(TxNodesFull(c))) == [Offer(2, c)]
    assert ecb.counters()["conflicts"] == 6


def test_requests_of_unknown_txnodes_bring_a_hello_per_gap_for_their_claims_only() -> None:
    ecb = Driver("full", recovery_ms=200)
    hello = [f for f in ecb.start(0) if isinstance(f, Hello)]
    ecb.tick(300)
    # a request from a TxNode nobody holds: counted, and Hello (a recovery window)
    assert ecb.rx(Request(SUB_BIND, 9, 0x5EED)) == hello
    # in that later window only the stray's claim is adopted (a burst of forged claims is not)
    assert ecb.rx(claim(9, 0x99), claim(10, 0x1010)) == []
    assert ecb.nodes() == {0x99: 9}
    ecb.tick(300)
    # another unknown TxNode within the Hello gap (10 s): no Hello; after it, one
    assert ecb.rx(Request(SUB_BIND, 11, 0x5EED)) == []
    ecb.tick(10_000)
    assert [f for f in ecb.rx(Request(SUB_BIND, 11, 0x5EED)) if isinstance(f, Hello)] == hello
    counters = ecb.counters()
    assert (counters["unassigned"], counters["adopted"], counters["conflicts"]) == (3, 1, 1)


def test_its_own_frames_heard_again_are_its_own() -> None:
    """A controller or an application that hands the CAN-ECB the frames it sent (an echo):
    they are not another CAN-ECB's (no Serving in answer, no correction, not counted)."""
    ecb = Driver("full", recovery_ms=100)
    sent = ecb.start(0) + ecb.tick(200)
    sent += ecb.census(0xE1) + ecb.census(0xE2)
    sent += ecb.rx(claim(0, 0xE1)) + ecb.rx(claim(1, 0xE2))
    assert {type(f) for f in sent} == {Hello, Serving, Census, Offer, Assign}
    echoed = [out for f in sent for out in ecb.rx(f)]
    assert echoed == []
    assert ecb.counters()["foreign_ecb_frames"] == 0
    assert ecb.rx(Assign(9, 0xE1)) != []  # another's, heard: corrected


def test_a_bind_is_not_corrected_as_a_join_frame() -> None:
    """A Bind (priority 1) whose etag field reads as an Assign's, TxNodesFull's or Failed's
    (0x20tt, 0x31tt, 0x37tt) and whose UID is a node id the table holds is a Bind: no Assign
    in answer, no conflict of the join's (found in review: the C CAN-ECB read the field alone)."""
    node = 0xAA01020304050607
    ecb = Driver("full", recovery_ms=100)
    ecb.start(0)
    assert ecb.rx(claim(5, node)) == []  # adopted in the recovery window
    ecb.tick(200)
    for etag in (0x2003, 0x3105, 0x3712):
        assert not [f for f in ecb.rx(Bind(etag, node)) if isinstance(f, Assign)], hex(etag)


def test_an_echo_is_its_own_only_within_its_window() -> None:
    """A frame it sent and hears again within a second is an echo; the same frame from another
    CAN-ECB 65.7 s later is another's, answered (its 16-bit time made it look fresh again)."""
    ecb = Driver("full", recovery_ms=100, lease_s=100_000)
    ecb.start(0)
    ecb.tick(200)
    sent = ecb.census(0xE1) + ecb.rx(claim(0, 0xE1))
    assign = next(f for f in sent if isinstance(f, Assign))
    ecb.tick(65_700)
    assert ecb.rx(assign) != []  # another's Assign, heard: Serving in answer
    assert ecb.counters()["foreign_ecb_frames"] == 1


def test_a_full_table_the_lease_and_the_blob_call_by_call() -> None:
    scenario_full_table("full")


def test_a_full_table_the_lease_and_the_blob_under_asan() -> None:
    build("asan", targets=VARIANTS, sources=SOURCES)  # built here, loaded in the child only
    code = "from tests.test_cecb_join import *; scenario_full_table('asan')"
    env = {**sanitizer_env(), "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=50)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
