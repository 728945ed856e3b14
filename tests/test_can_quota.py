"""The binding quota (docs/protocol.md, Bounds): what it counts, what it leaves alone, and that
it outlives a restart. Small quotas here; the default's figures are in test_can_forgery.py. In
one process, on python-can virtual buses, with real nodes and the real CAN-ECB."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path

import can
import pytest

from ups import Exhausted, Node, name_to_uid
from ups import _canproto as p

from .conftest import eventually, running_ecb
from .conftest import send_management as send

SMALL = (3, 2, 2, 2, 2)


async def test_a_node_past_its_quota_is_told_and_counted_and_may_use_what_exists(
    bus: str, tmp_path: Path
) -> None:
    async with (
        running_ecb(bus, tmp_path / "ecb.db", recovery=0.1, quota=SMALL) as ecb,
        Node(can=bus, node_id=1, join_timeout=10) as first,
        Node(can=bus, node_id=2, join_timeout=10) as second,
    ):
        await first.subscribe("a", "b", "c")
        with pytest.raises(Exhausted, match="no more channels"):
            await first.subscribe("d")
        assert ecb.counters["quota_hit"] >= 1 and name_to_uid("d") not in ecb.etags
        await first.subscribe("c")  # a channel it has: nothing new
        await second.subscribe("a", "b", "c", "x", "y")  # three exist: two new ones, its own
        await first.publish("x", b"1")  # bound by another: free for it
        assert ecb.creators == {
            name_to_uid(n): (1 if n in "abc" else 2) for n in ("a", "b", "c", "x", "y")
        }
    async with (
        running_ecb(bus, tmp_path / "large.db", recovery=0.1, quota=SMALL) as ecb,
        Node(can=bus, node_id=3, join_timeout=10) as third,
    ):
        big = bytes(100)  # size class 2 has a quota of its own (the node binds class 0 first,
        await third.publish("large/1", big)  # then moves the channel: its class-0 etag is
        await third.publish("large/2", big)  # free again, and no more its creation)
        with pytest.raises(Exhausted):
            await third.publish("large/3", big)
        assert len(ecb.etags) == 3  # large/1 and /2 in class 2, large/3 in class 0


async def test_the_quota_outlives_a_restart_of_the_can_ecb(bus: str, tmp_path: Path) -> None:
    db = tmp_path / "ecb.db"
    async with (
        running_ecb(bus, db, recovery=0.1, quota=SMALL),
        Node(can=bus, node_id=1, join_timeout=10) as node,
    ):
        await node.subscribe("a", "b", "c")
    with sqlite3.connect(db) as conn:
        assert conn.execute("SELECT COUNT(*) FROM creators").fetchone() == (3,)
    async with (
        running_ecb(bus, db, recovery=0.1, quota=SMALL) as ecb,
        Node(can=bus, node_id=1, join_timeout=10) as node,
    ):
        with pytest.raises(Exhausted):
            await node.subscribe("d")
        assert ecb.counters["quota_hit"] >= 1


async def test_a_binding_reported_after_a_lost_table_counts_against_its_reporter(
    bus: str, tmp_path: Path, raw_bus: can.BusABC
) -> None:
    """SUB_AT / PUB_AT of a pair in no table is adopted: a creation like any other. Past the
    quota it is not adopted (the reporter is told, Limit)."""
    async with (
        running_ecb(bus, tmp_path / "ecb.db", recovery=0.1, quota=SMALL) as ecb,
        Node(can=bus, node_id=1, join_timeout=10) as node,
    ):
        await eventually(lambda: not ecb.recovering)
        txnode = node.stats()["txnode"]
        for i in range(5):
            send(raw_bus, p.Holds(False, txnode, 0x100 + i, 0xAD0_0000 + i))
        await eventually(lambda: ecb.counters["requests"] >= 5 + 1)
        await eventually(lambda: ecb.counters["adopted"] + ecb.counters["quota_hit"] >= 5)
        assert ecb.counters["adopted"] == 3 and ecb.counters["quota_hit"] == 2
        assert len(ecb.etags) == 3


async def test_past_its_quota_a_node_gets_back_what_it_left_unused_past_the_lease(
    bus: str, tmp_path: Path
) -> None:
    async with (
        running_ecb(bus, tmp_path / "ecb.db", recovery=0.1, quota=SMALL, lease=0.3) as ecb,
        Node(can=bus, node_id=1, join_timeout=10) as node,
    ):
        subs = [await node.subscribe(n) for n in ("a", "b", "c")]
        for sub in subs[:2]:
            await sub.close()  # unused now: a and b may be reclaimed past the lease
        await eventually(lambda: not ecb.subscribers.get(name_to_uid("b")))
        await asyncio.sleep(0.4)  # the lease passes (what is being shown, not a synchronisation)
        await node.subscribe("d")
        assert ecb.counters["reclaimed"] == 1 and ecb.counters["quota_hit"] == 0
        kept = {n for n in ("a", "b", "c", "d") if name_to_uid(n) in ecb.etags}
        assert kept in ({"b", "c", "d"}, {"a", "c", "d"})  # one of the two unused ones went
        assert set(ecb.creators) == {name_to_uid(n) for n in kept}


async def test_rows_of_a_file_without_creators_count_against_nobody(
    bus: str, tmp_path: Path
) -> None:
    """A file written before the quota has no creators: its bindings are nobody's."""
    db = tmp_path / "old.db"
    with sqlite3.connect(db) as conn:
        conn.execute("CREATE TABLE txnodes (node_id TEXT PRIMARY KEY, txnode INTEGER UNIQUE)")
        conn.execute("CREATE TABLE etags (uid TEXT PRIMARY KEY, etag INTEGER UNIQUE NOT NULL)")
        conn.executemany(
            "INSERT INTO etags VALUES (?, ?)", [(f"{0xE0 + i:016x}", 0x10 + i) for i in range(5)]
        )
    async with (
        running_ecb(bus, db, recovery=0.1, quota=SMALL) as ecb,
        Node(can=bus, node_id=1, join_timeout=10) as node,
    ):
        await node.subscribe("a", "b", "c")
        assert len(ecb.etags) == 8 and len(ecb.creators) == 3
