"""What a CAN fuzz run (:mod:`benchmarks.can_fuzz`) watches and reports: what the CAN-ECB
handles (``EcbWatch``), the real traffic (``Flow``), every component's counters before and
after the flood (``Parts``), errors that reach the loop or the log (``watched``), and the
``Report`` a scenario prints and the tests check."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import resource
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ups import Node
from ups import _canproto as p
from ups._canlink import CanLink
from ups._message import Message
from ups._subscription import Subscription
from ups.broker.can_ecb import CanEcb

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


# --- counters and logs ----------------------------------------------------------------------------


def rss_kb() -> int:
    """This process's resident set (VmRSS), in KiB."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


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


def numeric(stats: dict[str, Any]) -> dict[str, Any]:
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
