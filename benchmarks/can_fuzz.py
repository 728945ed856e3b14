"""CAN fuzzing: a CAN-ECB, a gateway and a plain node under a flood of random and semi-valid
frames, in one process on python-can ``virtual`` buses.

Each scenario sets up real nodes with real traffic, floods the bus with ``--frames`` frames from
a seeded generator (``--seed``) while the real publishers keep publishing, and then checks that
a new node can still join and bind. It prints, per target: frames sent, time and frames/s
processed (until the CAN-ECB and every node's queue are through the flood), the counters that
moved, TxNodes and etags held before and after, events delivered against events published
during the flood, wrong deliveries, and the process's RSS before and after.

    .venv/bin/python -m ups.benchmarks.can_fuzz --frames 100000 --seed 1

The generator (``FrameGen``, in :mod:`benchmarks._can_frames`) mixes random, semi-valid and
forged frames, part of the time aimed at the scenario's channels and nodes (``Targets``).

Recovery windows open as the CAN-ECB decides: the flood's requests from TxNodes nobody holds
make it say Hello at most every 10 s, and the gateway's CAN-ECB then recovers for 2 s, the
standalone ones here for 0.2 s. The tests (tests/test_can_fuzz.py) pass ``recovery=0.2`` to
open exactly one short window at the flood's start instead (``prime_recovery``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import resource
import tempfile
import time
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from ups import Node, name_to_uid
from ups import _canproto as p
from ups._canface import CanFace
from ups._canlink import CanLink
from ups._message import Message
from ups._subscription import Subscription
from ups.benchmarks._can_frames import FrameGen, Targets
from ups.broker.can_ecb import HELLO_GAP, CanEcb
from ups.broker.tcp_ecb import TcpEcb
from ups.gateway import Gateway

BIG = 1 << 20  #: subscription queues that never drop during a flood
SETTLE = 10.0  #: seconds the real nodes get to bind every channel again after the flood

# --- watching the CAN-ECB --------------------------------------------------------------------


class EcbWatch:
    """Notes, for every node frame the CAN-ECB handles, whether the sending TxNode was held and
    whether the CAN-ECB was recovering; every node id a census completed; every Hello. Wraps
    three of its methods on the instance (instrumentation only: the library is unchanged)."""

    def __init__(self, ecb: CanEcb) -> None:
        self.ecb = ecb
        self.claims_in_recovery: set[int] = set()  #: node ids CLAIMed while recovering
        self.uids_from_held: set[int] = set()  #: UIDs named by frames from held TxNodes
        self.census_found: set[int] = set()
        self.recoveries = 0
        inner = ecb._on_management
        found = ecb._census._found
        hello = ecb._hello

        def on_management(msg: p.Management) -> None:
            if isinstance(msg, p.Request) and msg.kind == p.CLAIM:
                if ecb.recovering:
                    self.claims_in_recovery.add(msg.value)
            elif isinstance(msg, p.Request | p.Holds) and msg.txnode in ecb._txnodes.node_at:
                self.uids_from_held.add(msg.uid if isinstance(msg, p.Holds) else msg.value)
            inner(msg)

        def on_found(node_ids: list[int]) -> None:
            self.census_found.update(node_ids)
            found(node_ids)

        def on_hello() -> None:
            self.recoveries += 1
            hello()

        ecb._on_management = on_management  # type: ignore[method-assign]
        ecb._census._found = on_found
        ecb._hello = on_hello  # type: ignore[method-assign]

    def tables(self) -> dict[str, int]:
        """The sizes of the CAN-ECB's memory tables."""
        ecb = self.ecb
        return {
            "txnodes": len(ecb._store.txnodes),
            "etags": len(ecb._store.etags),
            "subscribers": len(ecb.subscribers),
            "publishers": len(ecb.publishers),
            "channels_of": len(ecb._channels.of),
            "asking": len(ecb._channels.asking),
            "deferred": len(ecb._etags.deferred),
            "declared": len(ecb._admission.declared),
            "refused_cache": len(ecb._admission._refused),
            "seen_etag": len(ecb._etags.seen),
            "gated": len(ecb._etags._gated),
        }


# --- real traffic ----------------------------------------------------------------------------


@dataclass
class Flow:
    """Channel ``name`` from a real publisher to one real subscription. The payload is the
    channel's name: an event from a real source with any other payload is a wrong delivery."""

    label: str
    name: str
    publisher: Node
    subscriber: Subscription
    real_sources: set[int]  #: msg.source of real nodes' events (TxNodes on CAN, ids on TCP)
    follows: Flow | None = None  #: the flow whose events this one hears too (same channel)
    sent: int = 0
    delivered: int = 0  #: from a real source, with the right payload
    forged: int = 0  #: from other sources (forged events: CAN has no authentication)
    wrong: list[Message] = field(default_factory=list)

    @property
    def payload(self) -> bytes:
        return self.name.encode()

    @property
    def published(self) -> int:
        return self.follows.sent if self.follows else self.sent

    async def publish(self) -> None:
        """Publish one event (a follower leaves it to the flow it follows)."""
        if self.follows is None:
            await self.publisher.publish(self.name, self.payload)
            self.sent += 1

    async def drain(self) -> int:
        """Check what arrived; return how many real events did."""
        got = 0
        while self.subscriber.pending:
            msg = await self.subscriber.get_msg(timeout=0)
            if msg.source not in self.real_sources:
                self.forged += 1
            elif msg.data != self.payload:
                self.wrong.append(msg)
            else:
                got += 1
        self.delivered += got
        return got

    def reset(self) -> None:
        self.sent = self.delivered = self.forged = 0
        self.wrong.clear()


# --- the report ------------------------------------------------------------------------------


@dataclass
class Report:
    target: str
    seed: int
    frames: int = 0
    seconds: float = 0.0
    generated: dict[str, int] = field(default_factory=dict)  #: by classify()
    kinds: dict[str, int] = field(default_factory=dict)  #: by how the frames were built
    samples: dict[str, str] = field(default_factory=dict)  #: first frame of each category
    counters: dict[str, dict[str, tuple[Any, Any]]] = field(default_factory=dict)
    tables_before: dict[str, int] = field(default_factory=dict)  #: the CAN-ECB's
    tables_after: dict[str, int] = field(default_factory=dict)
    extra: dict[str, tuple[Any, Any]] = field(default_factory=dict)  #: other sizes, before/after
    flows: dict[str, dict[str, int]] = field(default_factory=dict)
    wrong: list[str] = field(default_factory=list)
    rss_kb: tuple[int, int] = (0, 0)
    forged_txnode_holders: set[int] = field(default_factory=set)  #: node ids nobody runs
    txnodes_outside_recovery: set[int] = field(default_factory=set)  #: must stay empty
    new_uids: set[int] = field(default_factory=set)  #: UIDs bound during the flood
    uids_from_unheld: set[int] = field(default_factory=set)  #: must stay empty
    uids_from_held: int = 0  #: distinct UIDs in frames from held TxNodes (an upper bound)
    held_txnodes: int = 0
    recoveries: int = 0  #: Hellos the CAN-ECB sent during the run (recovery windows)
    moved: dict[str, tuple[int, int]] = field(default_factory=dict)  #: real nodes' TxNodes
    handler_errors: dict[str, int] = field(default_factory=dict)
    loop_errors: list[str] = field(default_factory=list)
    logged_errors: list[str] = field(default_factory=list)
    settle_error: str | None = None
    after_flood: dict[str, bool] = field(default_factory=dict)  #: flow -> an event arrived
    late_join: str = "not tried"  #: a new node joins and binds: "ok" or what went wrong
    late_event: bool = False  #: and an event of a real publisher reaches it
    standby: bool = False

    def moved_counters(self) -> dict[str, dict[str, tuple[Any, Any]]]:
        return {
            who: {k: v for k, v in c.items() if v[0] != v[1]} for who, c in self.counters.items()
        }

    def delta(self, who: str, key: str) -> int:
        before, after = self.counters[who][key]
        return int(after) - int(before or 0)

    def print(self) -> None:
        rate = self.frames / self.seconds if self.seconds else 0.0
        print(f"== {self.target} (seed {self.seed})")
        print(f"frames sent {self.frames}, processed in {self.seconds:.2f} s: {rate:,.0f} frames/s")
        print(f"  by kind: {dict(sorted(self.generated.items()))}")
        print(f"RSS {self.rss_kb[0] / 1024:.1f} MiB before, {self.rss_kb[1] / 1024:.1f} MiB after")
        print("counters that moved:")
        for who, moved in self.moved_counters().items():
            text = ", ".join(f"{k} {a}->{b}" for k, (a, b) in sorted(moved.items()))
            print(f"  {who}: {text or '(none)'}")
        print(f"CAN-ECB tables before: {self.tables_before}")
        print(f"CAN-ECB tables after:  {self.tables_after}")
        if self.extra:
            print(f"other sizes (before, after): {self.extra}")
        print(
            f"TxNodes held by node ids nobody runs: {len(self.forged_txnode_holders)} "
            f"(handed out outside recovery and census: {len(self.txnodes_outside_recovery)}); "
            f"Hellos (recovery windows): {self.recoveries}"
        )
        print(
            f"etags bound to new UIDs: {len(self.new_uids)} (asked for only by TxNodes nobody "
            f"held: {len(self.uids_from_unheld)}; UIDs named by held TxNodes: "
            f"{self.uids_from_held}, {self.held_txnodes} TxNodes held)"
        )
        for label, f in self.flows.items():
            print(
                f"  flow {label}: published {f['published']}, delivered {f['delivered']} "
                f"during the flood; forged events accepted {f['forged']}, wrong {f['wrong']}"
            )
        print(f"wrong deliveries: {self.wrong or 'none'}")
        print(f"real nodes moved: {self.moved or 'none'}; handler errors: {self.handler_errors}")
        print(f"events after the flood: {self.after_flood}; settled: {self.settle_error or 'yes'}")
        print(
            f"a new node joins and binds: {self.late_join}, hears a real publisher: "
            f"{self.late_event}; CAN-ECB stands by: {self.standby}"
        )
        print(f"exceptions in the loop: {self.loop_errors[:5] or 'none'}")
        print(f"ERROR log records: {len(self.logged_errors)} {self.logged_errors[:5]}")


# --- helpers ---------------------------------------------------------------------------------


def rss_kb() -> int:
    """This process's resident set (VmRSS), in KiB."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


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


class _ErrorLog(logging.Handler):
    """Keeps every ERROR record (and its exception) logged while a scenario runs."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        text = f"{record.name}: {record.getMessage()}"
        if record.exc_info and record.exc_info[1] is not None:
            text += f" [{type(record.exc_info[1]).__name__}: {record.exc_info[1]}]"
        self.records.append(text)


@contextlib.asynccontextmanager
async def watched(report: Report) -> AsyncIterator[None]:
    """Collect the exceptions that reach the event loop, and ERROR log records."""
    loop = asyncio.get_running_loop()
    previous = loop.get_exception_handler()
    handler = _ErrorLog()
    root = logging.getLogger()
    root.addHandler(handler)

    def on_error(_loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        report.loop_errors.append(f"{context.get('message')}: {context.get('exception')!r}")

    loop.set_exception_handler(on_error)
    try:
        yield
    finally:
        loop.set_exception_handler(previous)
        root.removeHandler(handler)
        report.logged_errors = handler.records


def link_stats(link: CanLink) -> dict[str, int]:
    return {
        "rx_frames": link.rx_frames,
        "tx_frames": link.tx_frames,
        "tx_failed": link.tx_failed,
        "rx_errors": link.rx_errors,
        "handler_errors": link.handler_errors,
    }


def _link_stats_of(node: Node) -> Callable[[], dict[str, Any]]:
    link = can_face(node).link
    return lambda: dict(link_stats(link))


def _numeric(stats: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in stats.items() if isinstance(v, int | bool)}


class Parts:
    """The counters of every component, read before and after the flood."""

    def __init__(self) -> None:
        self.sources: dict[str, Callable[[], dict[str, Any]]] = {}
        self.before: dict[str, dict[str, Any]] = {}

    def add(self, who: str, stats: Callable[[], dict[str, Any]]) -> None:
        self.sources[who] = stats

    def snap(self) -> None:
        self.before = {who: dict(stats()) for who, stats in self.sources.items()}

    def compare(self) -> dict[str, dict[str, tuple[Any, Any]]]:
        out = {}
        for who, stats in self.sources.items():
            now = stats()
            out[who] = {k: (self.before.get(who, {}).get(k), v) for k, v in now.items()}
        return out


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


# --- the scenarios ---------------------------------------------------------------------------


async def scenario_ecb(
    bus: str,
    workdir: Path,
    frames: int,
    seed: int,
    *,
    recovery: float | None = None,
    **targets: Any,
) -> Report:
    """A standalone CAN-ECB and three nodes: fz/a from P to S and Q, fz/b from P to S, fz/c
    from S to Q. Afterwards a fourth node joins, subscribes to fz/a and binds fz/new."""
    report = Report("CAN-ECB + nodes", seed, frames)
    raw = open_raw(bus)
    link = CanLink.open(bus)
    try:
        ecb = CanEcb(link, workdir / "ecb.db", recovery=0.2, max_channels=32)
        watch = EcbWatch(ecb)
        async with watched(report), contextlib.AsyncExitStack() as stack:
            await ecb.start()
            stack.callback(ecb.close)
            nodes = [Node(can=bus, node_id=0xF000 + i, join_timeout=10) for i in range(3)]
            for node in nodes:
                stack.push_async_callback(node.close)
            await asyncio.gather(*(n.start() for n in nodes))
            pub, sub, other = nodes
            txnodes = {n.node_id: can_face(n).txnode for n in nodes}
            real = {t for t in txnodes.values() if t is not None}
            a_to_s = Flow("fz/a P->S", "fz/a", pub, await sub.subscribe("fz/a", maxlen=BIG), real)
            flows = [
                a_to_s,
                Flow("fz/b P->S", "fz/b", pub, await sub.subscribe("fz/b", maxlen=BIG), real),
                Flow("fz/a P->Q", "fz/a", pub, await other.subscribe("fz/a", maxlen=BIG), real,
                     follows=a_to_s),
                Flow("fz/c S->Q", "fz/c", sub, await other.subscribe("fz/c", maxlen=BIG), real),
            ]  # fmt: skip
            await warm_up(flows)
            await eventually(lambda: not ecb.recovering)
            gen = FrameGen(seed, targets_for(ecb, ["fz/a", "fz/b", "fz/c"], real, **targets))
            parts = Parts()
            parts.add("can_ecb", lambda: _numeric(ecb.stats()))
            parts.add("ecb link", lambda: link_stats(link))
            for name, node in zip("PSQ", nodes, strict=True):
                parts.add(f"node {name}", node.stats)
                parts.add(f"link {name}", _link_stats_of(node))
            parts.snap()
            report.tables_before = watch.tables()
            uids_before = set(ecb.etags)
            links = [link, *(can_face(n).link for n in nodes)]
            prime_recovery(ecb, recovery)
            report.rss_kb = (rss_kb(), 0)
            report.seconds = await flood(raw, gen, frames, flows, link, links)
            report.rss_kb = (report.rss_kb[0], rss_kb())
            await settle(nodes, flows, report)
            report.late_join, report.late_event = await late_join(bus, 0xF010, "fz/new", flows[0])
            report.counters = parts.compare()
            report.moved = moved_nodes(nodes, txnodes)
            report.handler_errors = {
                "can_ecb": int(ecb.counters["handler_errors"]),
                **{f"link {i}": lk.handler_errors for i, lk in enumerate(links)},
            }
            legit = {*txnodes, 0xF010}
            finish(report, gen, watch, legit, uids_before, {name_to_uid("fz/new")})
    finally:
        link.close()
        raw.shutdown()
    return report


async def scenario_gateway(
    bus: str,
    workdir: Path,
    frames: int,
    seed: int,
    *,
    recovery: float | None = None,
    **targets: Any,
) -> Report:
    """A gateway (hosting the CAN-ECB) between the bus and a TCP-ECB on loopback. gw/up goes
    from CAN node CP to TCP node TS, gw/dn from TCP node TP to CAN node CS, gw/cc from CP to CS
    on CAN. Afterwards a new CAN node joins, subscribes to gw/dn and binds gw/new."""
    report = Report("gateway (CAN-ECB, CAN node, TCP node)", seed, frames)
    raw = open_raw(bus)
    tcp_ecb = TcpEcb("127.0.0.1", 0, recovery=0)
    await tcp_ecb.start()
    tcp_addr = f"127.0.0.1:{tcp_ecb.port}"
    try:
        async with watched(report), contextlib.AsyncExitStack() as stack:
            gw = Gateway(bus, tcp_addr, db=workdir / "gw.db", node_id=0x6A7E)
            stack.push_async_callback(gw.close)
            await gw.start()
            ecb, link, gw_can, gw_tcp = gw._ecb, gw._link, gw.can, gw.ip
            assert ecb is not None and link is not None and gw_can and gw_tcp
            watch = EcbWatch(ecb)
            cp = Node(can=bus, node_id=0xC0, name="can-pub", join_timeout=10)
            cs = Node(can=bus, node_id=0xC1, name="can-sub", join_timeout=10)
            tp = Node(broker=tcp_addr, node_id=0x70, name="tcp-pub")
            ts = Node(broker=tcp_addr, node_id=0x71, name="tcp-sub")
            for node in (cp, cs, tp, ts):
                stack.push_async_callback(node.close)
            await asyncio.gather(*(n.start() for n in (cp, cs, tp, ts)))
            can_nodes = [gw_can, cp, cs]
            txnodes = {n.node_id: can_face(n).txnode for n in can_nodes}
            real = {t for t in txnodes.values() if t is not None}
            gw_tx = can_face(gw_can).txnode
            assert gw_tx is not None
            flows = [
                Flow("gw/up CAN->TCP", "gw/up", cp, await ts.subscribe("gw/up", maxlen=BIG),
                     {gw_can.node_id}),
                Flow("gw/dn TCP->CAN", "gw/dn", tp, await cs.subscribe("gw/dn", maxlen=BIG),
                     {gw_tx}),
                Flow("gw/cc CAN->CAN", "gw/cc", cp, await cs.subscribe("gw/cc", maxlen=BIG),
                     real),
            ]  # fmt: skip
            await warm_up(flows)
            await eventually(lambda: not ecb.recovering)
            # forged events on gw/up's etag would reach TCP from the gateway's own node id,
            # indistinguishable from real ones: the generator sends none there
            up = ecb.etags[name_to_uid("gw/up")]
            names = ["gw/up", "gw/dn", "gw/cc"]
            gen = FrameGen(seed, targets_for(ecb, names, real, protected={up}, **targets))
            parts = Parts()
            parts.add("can_ecb", lambda: _numeric(ecb.stats()))
            parts.add("gateway", gw.stats)
            parts.add("gateway link", lambda: link_stats(link))
            for name, node in (("gateway CAN", gw_can), ("CP", cp), ("CS", cs)):
                parts.add(f"node {name}", node.stats)
            for name, node in (("CP", cp), ("CS", cs)):
                parts.add(f"link {name}", _link_stats_of(node))
            parts.add("node gateway TCP", gw_tcp.stats)
            parts.add("node TS", ts.stats)
            parts.add("node TP", tp.stats)
            parts.snap()
            report.tables_before = watch.tables()
            sizes_before = _gateway_sizes(gw, tcp_ecb)
            uids_before = set(ecb.etags)
            links = [link, can_face(cp).link, can_face(cs).link]
            prime_recovery(ecb, recovery)
            report.rss_kb = (rss_kb(), 0)
            report.seconds = await flood(raw, gen, frames, flows, link, links)
            report.rss_kb = (report.rss_kb[0], rss_kb())
            await settle(can_nodes, flows, report)
            report.late_join, report.late_event = await late_join(bus, 0xC2, "gw/new", flows[1])
            report.counters = parts.compare()
            sizes_after = _gateway_sizes(gw, tcp_ecb)
            report.extra = {k: (sizes_before[k], v) for k, v in sizes_after.items()}
            report.moved = moved_nodes(can_nodes, txnodes)
            report.handler_errors = {
                "can_ecb": int(ecb.counters["handler_errors"]),
                **{f"link {i}": lk.handler_errors for i, lk in enumerate(links)},
            }
            legit = {*txnodes, 0xC2}
            finish(report, gen, watch, legit, uids_before, {name_to_uid("gw/new")})
    finally:
        await tcp_ecb.close()
        raw.shutdown()
    return report


def _gateway_sizes(gw: Gateway, tcp_ecb: TcpEcb) -> dict[str, int]:
    return {
        "forwarding_to_can": len(gw._to_can_sinks),
        "forwarding_to_tcp": len(gw._to_ip_sinks),
        "gateway_can_channels": len(gw.can._states) if gw.can else 0,
        "gateway_tcp_channels": len(gw.ip._states) if gw.ip else 0,
        "tcp_ecb_subscribed_channels": len(tcp_ecb._subscribers),
        "gateway_reconcile_backlog": len(gw._dirty),
    }


async def scenario_node(
    bus: str,
    workdir: Path,
    frames: int,
    seed: int,
    *,
    recovery: float | None = None,
    **targets: Any,
) -> Report:
    """Node N with ``filter_limit=0`` (it hears every frame and filters in software) subscribes
    to nd/a and nd/x and publishes nd/b; helper node H publishes nd/a and nd/x and subscribes to
    nd/b. A CAN-ECB serves the bus. Afterwards a new node joins, subscribes to nd/a, binds
    nd/new."""
    report = Report("node (filter_limit=0)", seed, frames)
    raw = open_raw(bus)
    link = CanLink.open(bus)
    try:
        ecb = CanEcb(link, workdir / "ecb.db", recovery=0.2, max_channels=32)
        watch = EcbWatch(ecb)
        async with watched(report), contextlib.AsyncExitStack() as stack:
            await ecb.start()
            stack.callback(ecb.close)
            target = Node(can=bus, node_id=0xD0, join_timeout=10, filter_limit=0)
            helper = Node(can=bus, node_id=0xD1, join_timeout=10)
            nodes = [target, helper]
            for node in nodes:
                stack.push_async_callback(node.close)
            await asyncio.gather(*(n.start() for n in nodes))
            txnodes = {n.node_id: can_face(n).txnode for n in nodes}
            real = {t for t in txnodes.values() if t is not None}
            flows = [
                Flow("nd/a H->N", "nd/a", helper, await target.subscribe("nd/a", maxlen=BIG),
                     real),
                Flow("nd/x H->N", "nd/x", helper, await target.subscribe("nd/x", maxlen=BIG),
                     real),
                Flow("nd/b N->H", "nd/b", target, await helper.subscribe("nd/b", maxlen=BIG),
                     real),
            ]  # fmt: skip
            await warm_up(flows)
            await eventually(lambda: not ecb.recovering)
            gen = FrameGen(seed, targets_for(ecb, ["nd/a", "nd/x", "nd/b"], real, **targets))
            target_link = can_face(target).link
            parts = Parts()
            parts.add("node N", target.stats)
            parts.add("link N", lambda: link_stats(target_link))
            parts.add("node H", helper.stats)
            parts.add("can_ecb", lambda: _numeric(ecb.stats()))
            parts.snap()
            report.tables_before = watch.tables()
            uids_before = set(ecb.etags)
            face = can_face(target)
            heard_before = len(face.bindings.heard)
            links = [link, target_link, can_face(helper).link]
            prime_recovery(ecb, recovery)
            report.rss_kb = (rss_kb(), 0)
            report.seconds = await flood(raw, gen, frames, flows, link, links)
            report.rss_kb = (report.rss_kb[0], rss_kb())
            await settle(nodes, flows, report)
            report.late_join, report.late_event = await late_join(bus, 0xD2, "nd/new", flows[0])
            report.counters = parts.compare()
            report.extra = {"node N heard Binds of etags": (heard_before, len(face.bindings.heard))}
            report.moved = moved_nodes(nodes, txnodes)
            report.handler_errors = {
                "can_ecb": int(ecb.counters["handler_errors"]),
                **{f"link {i}": lk.handler_errors for i, lk in enumerate(links)},
            }
            legit = {*txnodes, 0xD2}
            finish(report, gen, watch, legit, uids_before, {name_to_uid("nd/new")})
    finally:
        link.close()
        raw.shutdown()
    return report


SCENARIOS = {"ecb": scenario_ecb, "gateway": scenario_gateway, "node": scenario_node}


async def _main(args: argparse.Namespace) -> None:
    for i, name in enumerate(args.targets.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            bus = f"virtual:can-fuzz-{name}-{i}-{time.monotonic_ns()}"
            report = await SCENARIOS[name](
                bus, Path(tmp), args.frames, args.seed, rivals=args.rivals, aim=args.aim
            )
            report.print()
            print(flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--targets", default="ecb,gateway,node", help="comma-separated")
    parser.add_argument(
        "--rivals",
        action="store_true",
        help="also Hello/Serving of any instance (the CAN-ECB may stand by for good)",
    )
    parser.add_argument(
        "--aim",
        type=float,
        default=0.1,
        help="how often an etag or UID field names a channel under test (default 0.1)",
    )
    parser.add_argument("--log", default="CRITICAL", help="log level of the daemons")
    args = parser.parse_args()
    logging.basicConfig(level=args.log)
    asyncio.run(_main(args))


if __name__ == "__main__":
    main()
