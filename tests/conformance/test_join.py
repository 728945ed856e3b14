"""Joining ("Joining: how a node gets its TxNode"): raw joiners against our CAN-ECB."""

from __future__ import annotations

import asyncio

from ups.broker.can_ecb import CanEcb

from ._frames import (
    MAX_TXNODE,
    Assign,
    Census,
    Knock,
    Offer,
    Query,
    Stage,
    claim,
    encode,
    nibbles,
)
from ._wire import RawNode, Wire

#: two ids that differ only in their last two nibbles (14 and 15)
NODE_A = 0x0123_4567_89AB_CD25
NODE_B = 0x0123_4567_89AB_CD3A


async def test_raw_joiner_gets_census_then_assign(raw: Wire, can_ecb: CanEcb) -> None:
    node_id = 0xFEDC_BA98_7654_3210
    joiner = RawNode(raw, node_id)
    txnode = await joiner.join()

    assert 0 <= txnode <= MAX_TXNODE
    assert txnode == 0, "the lowest free TxNode of an empty table"
    knock = next(i for i, h in enumerate(raw.log) if h.sent and h.frame == Knock())
    i_census, census = await raw.expect(Census, since=knock)
    assert 0 <= census.epoch <= 15
    stages = [h.frame for h in raw.log[i_census:] if h.sent and isinstance(h.frame, Stage)]
    expected = [Stage(census.epoch, s, n) for s, n in enumerate(nibbles(node_id))]
    assert stages[:16] == expected
    last_stage = max(i for i, h in enumerate(raw.log) if h.sent and h.frame in expected)
    # Offer(t, id); the joiner claims it from TxNode t; then Assign(t, id)
    i_offer, _ = await raw.expect(Offer(txnode, node_id), since=last_stage)
    i_claim = next(
        i for i, h in enumerate(raw.log) if i > i_offer and h.frame == claim(txnode, node_id)
    )
    await raw.expect(Assign(txnode, node_id), since=i_claim)


async def test_two_joiners_get_distinct_txnodes_after_a_query_per_branch(
    raw: Wire, can_ecb: CanEcb
) -> None:
    a, b = RawNode(raw, NODE_A), RawNode(raw, NODE_B)
    # both knock during the recovery window: one census finds them together
    ta, tb = await asyncio.gather(a.join(), b.join())

    assert ta != tb
    assert {ta, tb} == {0, 1}, "the lowest free TxNodes of an empty table"
    censuses = raw.find(Census)
    assert censuses, "no Census"
    queries = raw.find(Query)
    prefix_a, prefix_b = nibbles(NODE_A, 15), nibbles(NODE_B, 15)
    # the census hears nibbles 2 and 3 at stage 14: each extends the prefix into a new query
    assert sorted(q.prefix for q in queries) == [prefix_a, prefix_b], queries
    qa = next(q for q in queries if q.prefix == prefix_a)
    qb = next(q for q in queries if q.prefix == prefix_b)
    assert qa.epoch != qb.epoch
    first_query = next(i for i, h in enumerate(raw.log) if isinstance(h.frame, Query))
    census_before = [h.frame for h in raw.log[:first_query] if isinstance(h.frame, Census)]
    assert census_before, "a Query before any Census"
    assert census_before[-1].epoch not in (qa.epoch, qb.epoch), "an epoch reused at once"
    # identifier `01 eeee llll nnnn` (l = 15 nibbles - 1 = 14, n = the last nibble) and the
    # prefix's nibbles from the most significant one down, zero past the prefix
    assert encode(qa) == (
        0x7F << 14 | 0x1000 | qa.epoch << 8 | 14 << 4 | 0x2,
        bytes.fromhex("0123456789abcd20"),
    )
    assert encode(qb) == (
        0x7F << 14 | 0x1000 | qb.epoch << 8 | 14 << 4 | 0x3,
        bytes.fromhex("0123456789abcd30"),
    )
    assert raw.find(Offer(ta, NODE_A)) and raw.find(Offer(tb, NODE_B))
    assert raw.find(Assign(ta, NODE_A)) and raw.find(Assign(tb, NODE_B))


async def test_joiners_differing_in_the_last_nibble_need_no_query(
    raw: Wire, can_ecb: CanEcb
) -> None:
    a, b = RawNode(raw, 0x0123_4567_89AB_CDE5), RawNode(raw, 0x0123_4567_89AB_CDEA)
    ta, tb = await asyncio.gather(a.join(), b.join())

    assert ta != tb and {ta, tb} <= set(range(MAX_TXNODE + 1))
    # "when s = 15, into a whole id at once"
    assert not raw.find(Query)


async def test_a_node_joining_again_gets_its_txnode_back(raw: Wire, can_ecb: CanEcb) -> None:
    first = RawNode(raw, 0xAAAA)
    t_first = await first.join()
    first.close()
    other = RawNode(raw, 0xBBBB)
    t_other = await other.join()
    assert t_other != t_first

    again = RawNode(raw, 0xAAAA)
    assert await again.join() == t_first


async def test_an_offer_nobody_claims_lapses_and_a_late_claim_still_gets_it(
    raw: Wire, can_ecb: CanEcb
) -> None:
    """ "An Offer that nobody claims within the offer time lapses ... it gives their TxNodes to
    others only when no other TxNode is free ... and a late CLAIM(id) from a lapsed offer's
    TxNode gets that TxNode (stored, then Assign)"."""
    ghost = RawNode(raw, 0x6060)
    ghost.claim_offers = False
    knocking = asyncio.ensure_future(ghost.join(timeout=10.0))
    try:
        i_offer, offer = await raw.expect(
            lambda f: isinstance(f, Offer) and f.node_id == 0x6060, timeout=3.0
        )
    finally:
        knocking.cancel()
        ghost.close()
    await raw.expect_none(
        lambda f: isinstance(f, Assign) and f.node_id == 0x6060, since=i_offer, window=1.3
    )
    later = RawNode(raw, 0x6061)
    assert await later.join() != offer.txnode, "a lapsed offer's TxNode went to another"
    assert not raw.find(lambda f: isinstance(f, Assign) and f.node_id == 0x6060)
    late = raw.send(claim(offer.txnode, 0x6060))  # the slow node claims at last
    await raw.expect(lambda f: f == Assign(offer.txnode, 0x6060), since=late, timeout=3.0)


async def test_an_answer_missing_a_middle_stage_is_incomplete_and_asked_again(
    raw: Wire, can_ecb: CanEcb
) -> None:
    """ "a stage from |P| to 15 with no nibble (frames were lost ...): the answer is incomplete.
    The prefix known for certain ... is queried again". A census answer that lost its Stage
    frame of stage 7 is not read as complete (the stages before the gap are certain, those
    after it are not): the CAN-ECB sends Query(P = the first 7 nibbles), and the joiner's
    answer to that gets it its Offer (mutation audit, issue 41: counted as complete, it found
    nobody, asked nothing, and the joiner waited for another census)."""
    node_id, gap = 0xFEDC_BA98_7654_3210, 7
    ids = nibbles(node_id)
    _, census = await raw.expect(Census, since=raw.send(Knock()))
    answered = raw.send(*(Stage(census.epoch, s, ids[s]) for s in range(16) if s != gap))
    i_query, query = await raw.expect(Query, since=answered, timeout=5.0)
    assert query.prefix == nibbles(node_id, gap)
    assert not raw.find(Offer, since=answered, until=i_query), "an Offer from the torn answer"
    rest = raw.send(*(Stage(query.epoch, s, ids[s]) for s in range(gap, 16)))
    _, offer = await raw.expect(Offer, since=rest, timeout=5.0)
    assert offer.node_id == node_id
    assert can_ecb.stats()["census_incomplete"] == 1
