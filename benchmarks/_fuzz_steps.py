"""The steps of a CAN fuzz scenario (:mod:`benchmarks.can_fuzz`): warm the real traffic up,
flood the bus, let the real nodes settle, let a new node join, and fill in the report."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import can

from ups import Node, name_to_uid
from ups._canface import CanFace
from ups._canlink import CanLink
from ups.benchmarks._can_frames import FrameGen, Targets
from ups.benchmarks._fuzz_report import EcbWatch, Flow, Parts, Report, link_stats, rss_kb
from ups.broker.can_ecb import HELLO_GAP, CanEcb

SETTLE = 10.0  #: seconds the real nodes get to bind every channel again after the flood


async def eventually(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not predicate():
        if loop.time() > deadline:
            raise TimeoutError(f"condition not met within {timeout} s")
        await asyncio.sleep(0.002)


def can_face(node: Node) -> CanFace:
    face = node.face
    assert isinstance(face, CanFace)
    return face


def link_stats_of(node: Node) -> Callable[[], dict[str, Any]]:
    link = can_face(node).link
    return lambda: link_stats(link)


async def flood(
    raw: can.BusABC,
    gen: FrameGen,
    frames: int,
    flows: list[Flow],
    progress: CanLink,
    links: Iterable[CanLink],
    *,
    chunk: int = 250,
    backlog: int = 2000,
) -> float:
    """Send ``frames`` frames in chunks; after each chunk every flow publishes one event and the
    loop runs. Returns the seconds until ``progress`` (an unfiltered link) has handled them all
    and every link's receive queue is empty."""
    queues = [q for q in (getattr(link.bus, "queue", None) for link in links) if q is not None]
    start_rx = progress.rx_frames
    loop = asyncio.get_running_loop()
    start = loop.time()
    sent = 0
    while sent < frames:
        for _ in range(min(chunk, frames - sent)):
            raw.send(next(gen))
        sent = min(frames, sent + chunk)
        for f in flows:
            await f.publish()
        await asyncio.sleep(0)
        for f in flows:
            await f.drain()
        # let the receivers catch up
        await eventually(lambda: all(q.qsize() <= backlog for q in queues), timeout=300)
    await eventually(
        lambda: progress.rx_frames - start_rx >= frames and all(q.empty() for q in queues),
        timeout=300,
    )
    seconds = loop.time() - start
    for _ in range(3):
        await asyncio.sleep(0)
    for f in flows:
        await f.drain()
    return seconds


async def settle(nodes: list[Node], flows: list[Flow], report: Report) -> None:
    """Record the flood's deliveries; wait until every real CAN node relies on a binding for
    each of its channels again; then publish on every flow until one event arrives."""
    for f in flows:
        report.flows[f.label] = {
            "published": f.published,
            "delivered": f.delivered,
            "forged": f.forged,
            "wrong": len(f.wrong),
        }
    faces = [can_face(n) for n in nodes if isinstance(n.face, CanFace)]
    try:
        await eventually(lambda: not any(unbound(f) for f in faces), timeout=SETTLE)
    except TimeoutError:
        report.settle_error = f"still unbound after {SETTLE:g} s: " + ", ".join(
            f"TxNode {f.txnode}: {[why_unbound(f, uid) for uid in unbound(f)]}" for f in faces
        )
    arrived = dict.fromkeys((f.label for f in flows), False)
    for _ in range(50):  # 50 rounds of 20 ms at most
        for f in flows:
            await f.publish()
        await asyncio.sleep(0.02)
        for f in flows:
            if await f.drain():
                arrived[f.label] = True
        if all(arrived.values()):
            break
    report.after_flood = arrived
    report.wrong = [
        f"{f.label}: {m.data!r} from source {m.source} at priority {m.priority:#x}"
        for f in flows
        for m in f.wrong
    ]


def unbound(face: CanFace) -> list[int]:
    """The UIDs that ``face``'s node uses but holds no binding of."""
    return [
        uid
        for uid, state in face._channels.items()
        if (state.subs or state.published) and uid not in face.bindings.bound
    ]


def why_unbound(face: CanFace, uid: int) -> str:
    """``uid`` and what its node's binding of it is waiting for."""
    b = face.bindings
    task = face._rebinding.get(uid)
    heard = [f"{etag:#x}" for etag, other in b.heard.items() if other == uid]
    return (
        f"{uid:#x} (rebinding: {'none' if task is None else 'done' if task.done() else 'runs'}, "
        f"pending: {uid in b.pending}, candidate: {b._candidates.get(uid, (None,))[0]}, "
        f"refused: {uid in b._refused}, heard at: {heard})"
    )


async def late_join(bus: str | CanLink, node_id: int, fresh: str, flow: Flow) -> tuple[str, bool]:
    """A new node joins, subscribes to ``flow``'s channel and to a fresh one (a new etag).
    Returns "ok" or what went wrong, and whether an event of ``flow`` reached it."""
    try:
        async with Node(can=bus, node_id=node_id, join_timeout=10) as node:
            sub = await node.subscribe(flow.name)
            await node.subscribe(fresh)
            for _ in range(100):
                await flow.publish()
                with contextlib.suppress(TimeoutError):
                    msg = await sub.get_msg(timeout=0.05)
                    if msg.data != flow.payload:
                        return f"wrong payload {msg.data!r} on {flow.name}", False
                    return "ok", True
            return "ok", False
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}", False


async def warm_up(flows: list[Flow]) -> None:
    """Publish until every flow delivered once (every binding and route is in place)."""
    pending = list(flows)
    for _ in range(250):
        for f in flows:
            await f.publish()
        await asyncio.sleep(0.02)
        pending = [f for f in pending if not await f.drain()]
        if not pending:
            break
    else:
        raise TimeoutError(f"no traffic on {[f.label for f in pending]} before the flood")
    await asyncio.sleep(0.05)
    for f in flows:
        await f.drain()
        f.reset()


def open_raw(bus: str) -> can.BusABC:
    """A plain python-can bus on ``bus``, to inject the flood."""
    return can.Bus(interface="virtual", channel=bus.partition(":")[2])


def finish(
    report: Report,
    gen: FrameGen,
    watch: EcbWatch,
    legit_ids: set[int],
    uids_before: set[int],
    legit_uids: set[int],
) -> None:
    """Fill in what the generator sent and what the CAN-ECB holds now."""
    ecb = watch.ecb
    report.generated = dict(gen.counts)
    report.kinds = dict(gen.kinds)
    report.samples = {
        k: f"{m.arbitration_id:#010x} {bytes(m.data).hex()}" for k, m in gen.samples.items()
    }
    report.tables_after = watch.tables()
    report.recoveries = watch.recoveries
    forged = set(ecb.txnodes) - legit_ids
    report.forged_txnode_holders = forged
    report.txnodes_outside_recovery = forged - watch.claims_in_recovery - watch.census_found
    report.new_uids = set(ecb.etags) - uids_before - legit_uids
    report.uids_from_unheld = report.new_uids - watch.uids_from_held
    report.uids_from_held = len(watch.uids_from_held)
    report.held_txnodes = len(ecb.txnodes)
    report.standby = ecb.standby


def moved_nodes(nodes: list[Node], txnodes: dict[int, int | None]) -> dict[str, tuple[int, int]]:
    """The real nodes whose TxNode changed: node id -> (before, now); -1 for none."""
    out = {}
    for node in nodes:
        before, now = txnodes[node.node_id], can_face(node).txnode
        if now != before:
            out[f"{node.node_id:#x}"] = (
                -1 if before is None else before,
                -1 if now is None else now,
            )
    return out


def prime_recovery(ecb: CanEcb, recovery: float | None) -> None:
    """With ``recovery`` set: from now on the CAN-ECB recovers for that long after its Hello,
    and its Hello gap is over, so that the flood's first request from a TxNode nobody holds
    opens a recovery window at once (else whether one opens during the flood depends on how
    long ago the CAN-ECB last said Hello). CLAIMs heard in the window are adopted."""
    if recovery is not None:
        ecb._recovery = recovery
        for name in ("_last_unknown_hello", "_last_hello"):  # its name, in either version
            if hasattr(ecb, name):
                setattr(ecb, name, -HELLO_GAP)


def targets_for(ecb: CanEcb, names: list[str], real: set[int], **options: Any) -> Targets:
    """The generator's aim in a scenario; ``options`` are further ``Targets`` fields."""
    return Targets(
        etags=[ecb.etags[name_to_uid(n)] for n in names],
        uids=[name_to_uid(n) for n in names],
        txnodes=real,
        instance=ecb.instance,
        **options,
    )


@dataclass
class Scene:
    """What a scenario set up before its flood."""

    bus: str
    raw: can.BusABC  #: where the flood is sent from
    watch: EcbWatch  #: the CAN-ECB serving the bus, watched
    link: CanLink  #: the CAN-ECB's link: it hears every frame of the flood
    node_links: list[CanLink]  #: the real nodes' own links (the flood is through when they are)
    nodes: list[Node]  #: the real CAN nodes
    txnodes: dict[int, int | None]  #: their node ids and TxNodes before the flood
    flows: list[Flow]
    parts: Parts
    sizes: Callable[[], dict[str, int]] = dict  #: other sizes, for the report before and after


async def run_flood(
    scene: Scene,
    report: Report,
    gen: FrameGen,
    *,
    late: tuple[int, str, Flow],
    recovery: float | None,
) -> None:
    """Flood ``scene``'s bus with ``report.frames`` frames of ``gen``, let the real nodes settle,
    let a new node (``late``: its node id, a fresh channel, a flow to hear) join, and fill in
    ``report``."""
    watch, ecb = scene.watch, scene.watch.ecb
    links = [scene.link, *scene.node_links]
    scene.parts.snap()
    report.tables_before = watch.tables()
    sizes_before = scene.sizes()
    uids_before = set(ecb.etags)
    prime_recovery(ecb, recovery)
    report.rss_kb = (rss_kb(), 0)
    report.seconds = await flood(scene.raw, gen, report.frames, scene.flows, scene.link, links)
    report.rss_kb = (report.rss_kb[0], rss_kb())
    await settle(scene.nodes, scene.flows, report)
    node_id, fresh, flow = late
    report.late_join, report.late_event = await late_join(scene.bus, node_id, fresh, flow)
    report.counters = scene.parts.compare()
    report.extra = {k: (sizes_before[k], v) for k, v in scene.sizes().items()}
    report.moved = moved_nodes(scene.nodes, scene.txnodes)
    report.handler_errors = {
        "can_ecb": int(ecb.counters["handler_errors"]),
        **{f"link {i}": lk.handler_errors for i, lk in enumerate(links)},
    }
    legit = {*scene.txnodes, node_id}
    finish(report, gen, watch, legit, uids_before, {name_to_uid(fresh)})
