"""A flood of strays' requests and CLAIMs cannot lock new nodes out ("Restarts, recovery and
the answer to Hello": probation; *Bounds*, TxNodes). A forger sends a request from every TxNode
nobody holds (the CAN-ECB says Hello and recovers: a later window, for strays only) and then a
CLAIM of each with a made-up node id: every TxNode is taken. Those TxNodes are on probation
until a frame of theirs comes after the CLAIM, and a join that finds none free reclaims the
lowest of them instead of answering TxNodesFull. A CLAIM of a held TxNode by another id in such
a window moves that id to a TxNode of its own: when it held none before, that TxNode is on
probation too."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from ups import name_to_uid

from ._frames import MAX_TXNODE, SUB_BIND, Assign, Hello, TxNodesFull, claim, sub_bind
from ._wire import Ecb, RawNode, Wire, serving_ecb

UID = name_to_uid("conformance/probation")
HELD_UID = name_to_uid("conformance/probation/held")  #: asked only by ``_held``'s node
FORGED_ID = 0xF00D_0000  #: + TxNode: the forger's made-up node ids
#: the recovery windows: long enough for the CAN-ECB to handle 126 CLAIMs in one on a busy
#: machine (each adoption is stored before the next frame: the C one's blob is written anew)
RECOVERY = 1.0


@pytest.fixture
async def ecb(raw: Wire, channel: str, tmp_path: Path, ecb_kind: str) -> AsyncIterator[Ecb]:
    async with serving_ecb(channel, tmp_path / "ecb.db", ecb_kind, recovery=RECOVERY) as ecb:
        yield ecb


@pytest.fixture
async def instance(raw: Wire, ecb: Ecb) -> int:
    _, hello = await raw.expect(Hello)
    return int(hello.instance)


async def _flood(raw: Wire, instance: int) -> tuple[RawNode, list[int]]:
    """A real node joins; then the flood takes every other TxNode. The strays, lowest first."""
    real = RawNode(raw, 0x5EA1)
    await real.join()  # after the first recovery window: the next one is for strays only
    strays = [t for t in range(MAX_TXNODE + 1) if t != real.txnode]
    since = raw.send(*(sub_bind(t, UID) for t in strays))
    await raw.expect(Hello(instance), since=since, timeout=3.0)  # a window for strays
    raw.send(*(claim(t, FORGED_ID + t) for t in strays))  # heard in that window: adopted
    await _held(raw, strays[-1])
    return real, strays


async def _held(raw: Wire, txnode: int) -> None:
    """The CLAIM of ``txnode`` by ``FORGED_ID + txnode`` was heard in the window (adopted): a
    request from it is answered, which takes it off probation. (A CLAIM heard after the window
    is ignored: a test would then pass without probation.)"""
    node = RawNode(raw, FORGED_ID + txnode, txnode=txnode)
    try:
        await node.ask(SUB_BIND, HELD_UID, timeout=3.0)  # answered after the window
    finally:
        node.close()


async def _joins(raw: Wire, node_id: int) -> int:
    """A new node joins within 5 s (no TxNodesFull); its TxNode."""
    node = RawNode(raw, node_id)
    since = raw.mark()
    try:
        txnode = await node.join(timeout=5.0)
    finally:
        node.close()
    assert not raw.find(TxNodesFull(node_id), since=since)
    return txnode


async def test_a_flood_of_strays_claims_cannot_lock_a_new_node_out(
    raw: Wire, instance: int
) -> None:
    """Every TxNode is taken by forged ids that went silent after their CLAIM (the highest
    spoke: ``_flood``): a new node joins, on the lowest of them (reclaimed), and the next one on
    the next."""
    real, strays = await _flood(raw, instance)
    assert await _joins(raw, 0xA11CE) == strays[0]
    assert await _joins(raw, 0xB0B) == strays[1]
    await real.ask(SUB_BIND, UID)  # the real node keeps its TxNode
    assert not raw.find(lambda f: isinstance(f, Assign) and f.txnode == real.txnode
                        and f.node_id != real.node_id)  # fmt: skip


async def test_a_stray_that_speaks_again_is_off_probation(raw: Wire, instance: int) -> None:
    """The lowest stray asks again once it holds its TxNode (as a real node that asked while
    unknown does): it is answered, and a new node takes the next TxNode on probation, not
    its."""
    _, strays = await _flood(raw, instance)
    spoke = RawNode(raw, FORGED_ID + strays[0], txnode=strays[0])
    try:
        await spoke.ask(SUB_BIND, UID, timeout=3.0)  # held now: answered (after the window)
        assert await _joins(raw, 0xA11CE) == strays[1]
        assert not raw.find(lambda f: isinstance(f, Assign) and f.txnode == strays[0])
    finally:
        spoke.close()


async def test_a_flood_of_moves_cannot_lock_a_new_node_out(raw: Wire, instance: int) -> None:
    """One request from a TxNode nobody holds, then CLAIMs of it by as many made-up ids as
    there are TxNodes: the first is adopted, each other is moved to a TxNode of its own, on
    probation as it held none before. A new node joins."""
    real = RawNode(raw, 0x5EA1)
    await real.join()
    stray = 0 if real.txnode != 0 else 1
    since = raw.send(sub_bind(stray, UID))
    await raw.expect(Hello(instance), since=since, timeout=3.0)  # a window for the stray
    forged = [FORGED_ID + k for k in range(MAX_TXNODE + 1)]
    raw.send(*(claim(stray, node_id) for node_id in forged))
    await raw.expect(  # the last CLAIM was heard in the window: moved (or none was free yet)
        lambda f: isinstance(f, Assign | TxNodesFull) and f.node_id == forged[-1],
        since=since, timeout=5.0,
    )  # fmt: skip
    assert await _joins(raw, 0xA11CE) != real.txnode
    await real.ask(SUB_BIND, UID)  # the real node keeps its TxNode
    assert not raw.find(lambda f: isinstance(f, Assign) and f.txnode == real.txnode
                        and f.node_id != real.node_id)  # fmt: skip


async def test_a_node_on_probation_moved_back_to_its_own_txnode_stays_on_probation(
    raw: Wire, instance: int
) -> None:
    """A stray's CLAIM is adopted, then its id claims another TxNode: it is moved back to its
    own (Assign), but no frame of that TxNode came after the adopting CLAIM: it is still on
    probation, the lowest, and a new node takes it."""
    real = RawNode(raw, 0x5EA1)
    await real.join()
    strays = [t for t in range(MAX_TXNODE + 1) if t != real.txnode]
    since = raw.send(*(sub_bind(t, UID) for t in strays))
    await raw.expect(Hello(instance), since=since, timeout=3.0)
    moved = FORGED_ID + strays[0]
    raw.send(claim(strays[0], moved), claim(strays[1], moved))  # adopted, then moved back
    raw.send(*(claim(t, FORGED_ID + t) for t in strays[1:]))
    await raw.expect(Assign(strays[0], moved), since=since, timeout=3.0)
    await _held(raw, strays[-1])
    assert await _joins(raw, 0xA11CE) == strays[0]
