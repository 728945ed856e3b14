"""libups-ecb's binding half (c/ups_ecb_bind.c): etags in every size class and moves, Limit and
the quota, UNSUB, requests held in the recovery window, SUB_AT/PUB_AT adopted or contradicted,
the Roster's answers and the bound on those waiting, DECLARE, and the blob's section across a
restart.

Most tests run the compiled library as a CAN-ECB on a python-can virtual bus
(``broker/c_ecb.py``'s CEcb), against frames built from docs/protocol.md
(``tests/conformance/_frames``). The lease and a full table are driven call by call with the
time given explicitly (``Driver``), also in a child process under AddressSanitizer on the small
tables of the asan build (8 channels, 2 waiting Rosters)."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from tests.cecb_calls import Driver
from tests.conformance._frames import (
    PUB_BIND,
    ROSTER,
    SUB_BIND,
    UNSUB,
    Bind,
    Declare,
    EtagsFull,
    Event,
    Grant,
    Hello,
    Limit,
    Refuse,
    Request,
    RosterEnd,
    SubAt,
    Uses,
    encode,
)
from tests.conformance._wire import RawNode, Wire
from tests.procs import sanitizer_env
from ups._canlink import CanLink
from ups._cnode import build
from ups.broker._cecb_lib import SOURCES, VARIANTS
from ups.broker.c_ecb import CEcb

ROOT = Path(__file__).resolve().parent.parent
CLASS_FIRST = (0x0010, 0x3000, 0x3400, 0x3800, 0x3C00)  #: the first etag of each size class


def pub_bind(c: int, txnode: int, uid: int) -> Request:
    """PUB_BIND(c): an etag of size class c (1-4) or larger (etag field 0x0008 + c)."""
    return Request(0x08 + c, txnode, uid)


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
    w = Wire(f"cecb-bind-{request.node.name}-{id(request)}")
    yield w
    await w.close()


async def answer(wire: Wire, frame: Any, uid: int) -> Any:
    """Send ``frame``; the first Bind, EtagsFull or Limit of ``uid`` after it."""
    since = wire.send(frame)
    _, heard = await wire.expect(
        lambda f: isinstance(f, Bind | EtagsFull | Limit) and f.uid == uid, since=since
    )
    return heard


# --- on a virtual bus -----------------------------------------------------------------------


async def test_every_size_class_and_a_move_to_a_larger_one(wire: Wire, tmp_path: Path) -> None:
    async with c_ecb(wire.channel, tmp_path / "ecb.blob") as ecb:
        node = RawNode(wire, 0xB1)
        t = await node.join()
        for c in range(5):
            uid = 0xC1A5500 + c
            frame = Request(SUB_BIND, t, uid) if c == 0 else pub_bind(c, t, uid)
            assert await answer(wire, frame, uid) == Bind(CLASS_FIRST[c], uid)
        # a channel of class 0 asked for class 2: it moves to the next free etag of class 2
        small = 0xC1A5600
        assert await answer(wire, Request(SUB_BIND, t, small), small) == Bind(0x0011, small)
        assert await answer(wire, pub_bind(2, t, small), small) == Bind(0x3401, small)
        assert ecb.counters()["moved"] == 1
        # a larger class than asked is large enough: the same etag, also for SUB_BIND and class 1
        for frame in (Request(SUB_BIND, t, small), pub_bind(1, t, small)):
            assert await answer(wire, frame, small) == Bind(0x3401, small)
        # the old etag is free again: the next channel of class 0 gets it
        other = 0xC1A5700
        assert await answer(wire, Request(PUB_BIND, t, other), other) == Bind(0x0011, other)
        assert ecb.etags[small] == 0x3401 and ecb.counters()["bound"] == 8


async def test_limit_past_the_channels_of_a_txnode_and_past_the_quota(
    wire: Wire, tmp_path: Path
) -> None:
    async with c_ecb(wire.channel, tmp_path / "ecb.blob", max_channels=4,
                     quota=(2, 1, 1, 1, 1)) as ecb:  # fmt: skip
        a, b = RawNode(wire, 0xB2), RawNode(wire, 0xB3)
        ta, tb = await a.join(), await b.join()
        for uid in (0x100, 0x101):
            assert isinstance(await answer(wire, Request(SUB_BIND, ta, uid), uid), Bind)
        # a's quota of class 0 is spent: Limit, counted; b may bind what a created, for free
        assert await answer(wire, Request(SUB_BIND, ta, 0x102), 0x102) == Limit(ta, 0x102)
        assert ecb.counters()["quota_hit"] == 1
        assert isinstance(await answer(wire, Request(SUB_BIND, tb, 0x100), 0x100), Bind)
        assert isinstance(await answer(wire, Request(SUB_BIND, tb, 0x101), 0x101), Bind)
        # one of class 1, then the quota of class 1 is spent too
        assert await answer(wire, pub_bind(1, ta, 0x110), 0x110) == Bind(0x3000, 0x110)
        assert await answer(wire, pub_bind(1, ta, 0x111), 0x111) == Limit(ta, 0x111)
        assert ecb.counters()["quota_hit"] == 2
        # a uses four channels with one b created: a fifth is past max_channels (limited), a
        # channel it uses is not
        assert isinstance(await answer(wire, Request(PUB_BIND, tb, 0x200), 0x200), Bind)
        assert isinstance(await answer(wire, Request(SUB_BIND, ta, 0x200), 0x200), Bind)
        assert await answer(wire, Request(SUB_BIND, ta, 0x3C), 0x3C) == Limit(ta, 0x3C)
        assert ecb.counters()["limited"] == 1
        assert isinstance(await answer(wire, Request(PUB_BIND, ta, 0x100), 0x100), Bind)
        # UNSUB of a channel it only subscribes to: it counts no more (UNSUB gets no answer)
        since = wire.send(Request(UNSUB, ta, 0x101))
        assert isinstance(await answer(wire, Request(SUB_BIND, tb, 0x3C), 0x3C), Bind)
        assert isinstance(await answer(wire, Request(SUB_BIND, ta, 0x3C), 0x3C), Bind)
        assert await answer(wire, Request(SUB_BIND, ta, 0x101), 0x101) == Limit(ta, 0x101)
        assert ecb.counters()["limited"] == 2
        assert not wire.find(lambda f: isinstance(f, Bind) and f.uid == 0x101, since)


async def test_unsub_and_the_roster_of_who_uses_what(wire: Wire, tmp_path: Path) -> None:
    async with c_ecb(wire.channel, tmp_path / "ecb.blob") as ecb:
        nodes = [RawNode(wire, 0xB4 + n) for n in range(3)]
        t = [await node.join() for node in nodes]
        speed, brake = 0x5EED, 0xB4AE
        for txnode in t:
            await answer(wire, Request(SUB_BIND, txnode, speed), speed)
        await answer(wire, Request(PUB_BIND, t[2], speed), speed)
        await answer(wire, Request(PUB_BIND, t[0], brake), brake)
        wire.send(Request(UNSUB, t[1], speed), Request(UNSUB, t[0], brake))  # not a subscriber
        since = wire.send(Request(ROSTER, t[1], 0))
        i, end = await wire.expect(lambda f: isinstance(f, RosterEnd), since=since)
        uses = [f for f in wire.heard(since, i) if isinstance(f, Uses)]
        assert end == RosterEnd(t[1], 0, True)
        assert uses == [  # lowest UID first; subscribers, then publishers, lowest TxNode first
            Uses(False, t[0], speed), Uses(False, t[2], speed), Uses(True, t[2], speed),
            Uses(True, t[0], brake),
        ]  # fmt: skip
        counters = ecb.counters()
        assert (counters["rosters"], counters["roster_frames"]) == (1, len(uses) + 1)
        status = {c["uid"]: c for c in ecb.status()["channels"]}
        assert status[f"0x{speed:016x}"]["subscribers"] == [f"0x{t[0]:02x}", f"0x{t[2]:02x}"]


async def test_requests_held_in_recovery_and_reports_adopted_or_contradicted(
    wire: Wire, tmp_path: Path
) -> None:
    """Nodes already on the bus (a CAN-ECB that lost its table): their claims and reports are
    adopted in the recovery window; a new binding waits for its end; a report that contradicts
    the tables is answered with their Binds."""
    held = RawNode(wire, 0xB8, txnode=0x21)
    held.subs = {0xAAA: 0x0123}
    held.pubs = {0xBBB: 0x3456}
    async with c_ecb(wire.channel, tmp_path / "ecb.blob", recovery=1.0) as ecb:
        await wire.expect(Hello)  # answered at once: CLAIM, SUB_AT, PUB_AT
        since = wire.send(Request(SUB_BIND, 0x21, 0xCCC))  # a new binding: held
        assert await answer(wire, Request(SUB_BIND, 0x21, 0xAAA), 0xAAA) == Bind(0x0123, 0xAAA)
        assert not wire.find(lambda f: getattr(f, "uid", None) == 0xCCC, since)
        assert ecb.counters()["deferred"] >= 1
        _, bind = await wire.expect(
            lambda f: isinstance(f, Bind) and f.uid == 0xCCC, since=since, timeout=3.0
        )
        assert bind.etag == 0x0010  # the lowest etag nobody reported
        counters = ecb.counters()
        assert counters["adopted"] == 3  # its TxNode and both etags
        assert ecb.etags == {0xAAA: 0x0123, 0xBBB: 0x3456, 0xCCC: 0x0010}
        # a report that contradicts the tables: both Binds of the table, counted
        since = wire.send(SubAt(0x21, 0x0123, 0xBBB))
        await wire.expect(Bind(0x0123, 0xAAA), since=since)
        await wire.expect(Bind(0x3456, 0xBBB), since=since)
        assert ecb.counters()["conflicts"] == counters["conflicts"] + 1
        # after recovery, a report of a pair in no table is adopted as well
        wire.send(SubAt(0x21, 0x0222, 0xDDD))
        await answer(wire, Request(SUB_BIND, 0x21, 0xDDD), 0xDDD)
        assert ecb.etags[0xDDD] == 0x0222
        held.close()


async def test_declare_grant_refuse_and_the_state_across_a_restart(
    wire: Wire, tmp_path: Path
) -> None:
    state = tmp_path / "ecb.blob"
    quota = (1, 64, 64, 64, 64)
    node = RawNode(wire, 0xB9)
    async with c_ecb(wire.channel, state, quota=quota) as ecb:
        t = await node.join()
        etag = (await node.ask(PUB_BIND, 0x5117)).etag
        declare = Declare(t, etag, 1, 100, 50, 0)  # 1 byte every 10 ms, due within 5 ms
        since = wire.send(declare)
        _, grant = await wire.expect((Grant, Refuse), since=since)
        assert grant == Grant(etag, t, 0x02)
        since = wire.send(declare)  # the same again: the same answer
        assert (await wire.expect((Grant, Refuse), since=since))[1] == grant
        # 8 bytes due within 100 us: no frame is that fast at 500 kbit/s; nothing changes
        since = wire.send(Declare(t, etag, 8, 100, 1, 0))
        _, refuse = await wire.expect((Grant, Refuse), since=since)
        assert isinstance(refuse, Refuse)
        assert (refuse.etag, refuse.txnode, refuse.miss_txnode, refuse.miss_etag) == (
            etag,
            t,
            t,
            etag,
        )
        # a DECLARE of an etag it does not publish on is ignored
        since = wire.send(Declare(t, 0x0777, 1, 100, 50, 0))
        # past the quota of class 0 (1)
        assert await answer(wire, Request(SUB_BIND, t, 0x5118), 0x5118) == Limit(t, 0x5118)
        assert not wire.find((Grant, Refuse), since)
        counters = ecb.counters()
        assert (counters["admitted"], counters["refused"]) == (1, 1)
    # the same state file: the binding, its creator (the quota) and the admitted stream remain
    restarted = wire.mark()
    async with c_ecb(wire.channel, state, quota=quota) as ecb:
        await wire.expect(Hello, since=restarted)  # answered at once: CLAIM, PUB_AT
        assert ecb.etags == {0x5117: etag}
        assert await answer(wire, Request(SUB_BIND, t, 0x5118), 0x5118) == Limit(t, 0x5118)
        since = wire.send(declare)
        assert (await wire.expect((Grant, Refuse), since=since))[1] == grant
        assert ecb.counters()["admitted"] == 0  # answered as admitted before, no new analysis
    node.close()


# --- call by call -----------------------------------------------------------------------------


def scenario_full_table_and_the_lease(variant: str) -> None:
    """Requests held in the recovery window (UPS_ECB_HELD of them), then every channel of the
    table filled; EtagsFull (channels_full) until the lease has passed for a channel nobody
    uses, which is then reclaimed; the clock wraps meanwhile; the blob keeps the tables."""
    # the quota is not what this fills (the host build has room for more than one's quota)
    ecb = Driver(variant, step=10, lease_s=1, recovery_ms=300, quota=(0xFFFF,) * 5)
    ecb.now = 0xFFFFFE00  # the clock wraps in 0.5 s
    ecb.c.ups_ecb_start(ecb.state, ecb.now)
    ecb.take()
    for t in (1, 2):  # nodes claim in the recovery window after the Hello at start: adopted
        ecb.rx(Request(0x04, t, 0xD00 + t))
    n, held = ecb.config["channels"], ecb.config["held"]
    uids = [0xF000 + i for i in range(n)]
    # new bindings asked in the recovery window wait for its end; past UPS_ECB_HELD, dropped
    for i, uid in enumerate(uids[: held + 1]):
        assert ecb.rx(Request(SUB_BIND, 1 + i % 2, uid)) == []
    assert (ecb.counters()["deferred"], ecb.counters()["held_dropped"]) == (held, 1)
    answers = [f for f in ecb.tick(400) if isinstance(f, Bind)]
    assert answers == [Bind(0x10 + i, uid) for i, uid in enumerate(uids[:held])]
    for i, uid in enumerate(uids[held:], held):
        assert ecb.rx(Request(SUB_BIND, 1 + i % 2, uid)) == [Bind(0x10 + i, uid)]
    assert ecb.rx(Request(SUB_BIND, 1, 0xFFFF)) == [EtagsFull(0xFFFF)]
    assert ecb.counters()["channels_full"] == 1
    # node 1 leaves its channels; the lease has not passed yet: still full
    for uid in uids[::2]:
        assert ecb.rx(Request(UNSUB, 1, uid)) == []
    ecb.tick(500)
    assert ecb.rx(Request(SUB_BIND, 2, 0xFFFF)) == [EtagsFull(0xFFFF)]
    # an event keeps the first one in use; past the lease, the one unused longest is reclaimed
    ecb.tick(400)
    ecb.rx(Event(0x80, 2, 0x10, b"\x01"))
    ecb.tick(400)
    assert ecb.rx(Request(SUB_BIND, 2, 0xFFFF)) == [Bind(0x12, 0xFFFF)]
    assert ecb.counters()["reclaimed"] == 1
    # the blob's section round trip: the same tables in another CAN-ECB
    blob = ctypes.create_string_buffer(ecb.config["blob_max"])
    size = ecb.c.ups_ecb_save(ecb.state, blob, len(blob))
    other = Driver(variant, step=10)
    assert other.c.ups_ecb_restore(other.state, blob, size) == 0
    uid = ctypes.c_uint64()
    tables = [
        (other.c.ups_ecb_channel(other.state, i, ctypes.byref(uid)), uid.value) for i in range(n)
    ]
    assert sorted(tables) == sorted([(0x10 + i, u) for i, u in enumerate(uids) if i != 2]
                                    + [(0x12, 0xFFFF)])  # fmt: skip


def test_a_full_table_and_the_lease_call_by_call() -> None:
    scenario_full_table_and_the_lease("full")


def in_asan_child(scenario: str) -> None:
    """Run ``scenario('asan')`` of this file in a child process on the asan build (built here,
    loaded by the child only: ASan must be the first library it loads)."""
    build("asan", targets=VARIANTS, sources=SOURCES)
    code = f"from tests.test_cecb_bind import *; {scenario}('asan')"
    env = {**os.environ, **sanitizer_env(), "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=50)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.timeout(240)  # the asan build made here, then its child: minutes on a busy machine
def test_a_full_table_and_the_lease_under_asan() -> None:
    in_asan_child("scenario_full_table_and_the_lease")


def scenario_rosters_past_their_bound(variant: str) -> None:
    """UPS_ECB_ROSTERS Rosters wait at once, one per node: in a recovery window (nothing is
    answered) one more node than that asks; its Roster is not kept (rosters_full), a newer one
    of a node that waits replaces it at the back (roster_replaced), and when the window ends
    each kept one is answered, oldest first, the refused one not; asked again, it is."""
    ecb = Driver(variant, recovery_ms=300)
    bound = ecb.config["rosters"]
    askers = list(range(1, bound + 2))
    ecb.start(0)
    for t in askers:  # nodes claim in the recovery window after the Hello at start: adopted
        ecb.rx(Request(0x04, t, 0xD00 + t))
    for t in askers:
        assert ecb.rx(Request(ROSTER, t, 0)) == []  # answered when the window ends
    assert ecb.counters()["rosters_full"] == 1  # the last: as many of other nodes wait
    assert ecb.rx(Request(ROSTER, askers[0], 0)) == []  # waits: replaced, not refused
    assert (ecb.counters()["roster_replaced"], ecb.counters()["rosters_full"]) == (1, 1)
    ends = [f for f in ecb.tick(500) if isinstance(f, RosterEnd)]
    assert ends == [RosterEnd(t, 0, True) for t in askers[1:bound] + askers[:1]]
    again = ecb.rx(Request(ROSTER, askers[-1], 0)) + ecb.tick(50)  # its 2 s have passed
    assert [f for f in again if isinstance(f, RosterEnd)] == [RosterEnd(askers[-1], 0, True)]
    assert ecb.counters()["rosters_full"] == 1


def test_rosters_past_their_bound_call_by_call() -> None:
    scenario_rosters_past_their_bound("full")


@pytest.mark.timeout(240)  # the asan build made here, then its child: minutes on a busy machine
def test_rosters_past_their_bound_under_asan() -> None:
    """On the asan build's tables (UPS_ECB_ROSTERS 2), where a Roster kept past the table
    would write out of it."""
    in_asan_child("scenario_rosters_past_their_bound")


def test_an_admission_whose_grants_do_not_fit_the_tx_queue_waits_for_the_declare_again() -> None:
    """A DECLARE whose admission moves the priorities of other streams needs a Grant for each:
    with fewer free places in the TX queue than that, nothing is admitted or changed (counted in
    tx_dropped) and the node's DECLARE again gets them all (found in review: the Grants that did
    not fit were dropped and the priorities changed anyway, so a node never heard its new one)."""
    ecb = Driver("full", recovery_ms=100)
    ecb.start(0)
    ecb.rx(Request(0x04, 1, 0xD01))  # a node claims TxNode 1 in the recovery window: adopted
    ecb.tick(200)
    etags = [f.etag for uid in (0xA1, 0xA2, 0xA3) for f in ecb.rx(Request(PUB_BIND, 1, uid))
             if isinstance(f, Bind)]  # fmt: skip
    # two streams, then one due sooner than both: it goes on top and moves the two
    for etag, deadline in zip(etags[:2], (90, 80), strict=True):
        assert [f for f in ecb.rx(Declare(1, etag, 1, 1000, deadline, 0)) if isinstance(f, Grant)]
    urgent = Declare(1, etags[2], 1, 1000, 10, 0)

    def queue_only(frame: Any) -> None:  # ups_ecb_rx with nothing taken from the queue
        can_id, data = encode(frame)
        ecb.frame.id, ecb.frame.flags, ecb.frame.len = can_id, 0x01, len(data)
        ctypes.memmove(ecb.frame.data, data, len(data))
        ecb.c.ups_ecb_rx(ecb.state, ecb.now, ctypes.byref(ecb.frame))

    for i in range(ecb.config["tx_depth"] - 2):  # the queue full but for two places
        queue_only(Request(SUB_BIND, 1, 0xB000 + i))
    dropped = ecb.counters()["tx_dropped"]
    queue_only(urgent)
    assert ecb.counters()["tx_dropped"] == dropped + 1
    assert not [f for f in ecb.take() if isinstance(f, Grant)]  # none sent, none half-sent
    grants = [f for f in ecb.rx(urgent) if isinstance(f, Grant)]  # asked again: all three
    assert sorted(g.etag for g in grants) == sorted(etags)
    assert next(g for g in grants if g.etag == etags[2]).priority < min(
        g.priority for g in grants if g.etag != etags[2]
    )
