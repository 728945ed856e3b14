"""The CAN Event Channel Broker: gives TxNodes to joining nodes and binds channel UIDs to etags.

Exactly one CAN-ECB serves a bus, standalone (``ups can-broker``) or hosted by the gateway. Its
tables (node id -> TxNode, UID -> etag) live in an SQLite file, so a restarted CAN-ECB gives every
node and channel the same identifiers as before. Who publishes and subscribes what is soft
state: after a start the CAN-ECB says Hello and every node announces itself again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
from collections import defaultdict
from collections.abc import Awaitable, Callable
from fractions import Fraction
from math import ceil
from pathlib import Path

import can

from ups import _canproto as p
from ups._canlink import CanLink
from ups._errors import DecodeError
from ups.rt import MessageSpec, NotSchedulable, assign_priorities

log = logging.getLogger("ups.can_ecb")

RACE_TIMEOUT = 1.0  # a race whose leader fell silent this long starts again
#: A complete id is held this long before it wins, so that a lower id can still object. On a
#: real bus arbitration already lets the lowest id through first; buses emulated over IP or in
#: memory deliver simultaneous offers in any order.
SETTLE = 0.05
GATE_TIMEOUT = 1.0  # the longest a publisher's binding waits for the gateway
#: Priorities the CAN-ECB gives declared real-time streams; best-effort channels stay below
#: (0x80 by default), management frames above (0x00, 0x01).
RT_FIRST, RT_LAST = 0x02, 0x7F


class _Store:
    """The persistent tables, mirrored in dicts; every change is committed at once."""

    def __init__(self, path: str | Path) -> None:
        self._db = sqlite3.connect(str(path))
        self._db.executescript(
            """
            CREATE TABLE IF NOT EXISTS txnodes (node_id TEXT PRIMARY KEY,
                                                txnode INTEGER UNIQUE NOT NULL);
            CREATE TABLE IF NOT EXISTS etags (uid TEXT PRIMARY KEY, etag INTEGER UNIQUE NOT NULL);
            """
        )
        self.txnodes: dict[int, int] = {
            int(k, 16): v for k, v in self._db.execute("SELECT * FROM txnodes")
        }
        self.etags: dict[int, int] = {
            int(k, 16): v for k, v in self._db.execute("SELECT * FROM etags")
        }
        self.taken_etags = set(self.etags.values())

    def add_txnode(self, node_id: int, txnode: int) -> None:
        with self._db:
            self._db.execute("INSERT INTO txnodes VALUES (?, ?)", (f"{node_id:016x}", txnode))
        self.txnodes[node_id] = txnode

    def add_etag(self, uid: int, etag: int) -> None:
        with self._db:
            self._db.execute("INSERT INTO etags VALUES (?, ?)", (f"{uid:016x}", etag))
        self.etags[uid] = etag
        self.taken_etags.add(etag)

    def close(self) -> None:
        self._db.close()


class CanEcb:
    """The CAN-ECB of one bus.

    ``subscribers`` and ``publishers`` map each channel UID to the TxNodes that subscribe to or
    publish on it. ``on_change(uid)`` is called whenever either set of a channel changes (the
    gateway forwards by them). ``bind_gate(uid)``, when set, is awaited (at most
    ``GATE_TIMEOUT`` s) before a publisher's binding is answered, so that a gateway is
    forwarding the channel before its first event is sent.
    """

    def __init__(
        self,
        link: CanLink,
        db_path: str | Path = "ups-can-ecb.db",
        *,
        bitrate: int = 500_000,
        settle: float = SETTLE,
    ) -> None:
        self.link = link
        self._handler = self._on_frame  # one bound method, so the link can tell it apart
        self._store = _Store(db_path)
        self._epoch = 0
        self._prefix: list[int] = []
        self._race_timer: asyncio.TimerHandle | None = None
        self._settle = settle
        self.bitrate = bitrate
        #: (etag, TxNode) -> the declared real-time stream, and the priority it was granted
        self.declared: dict[tuple[int, int], MessageSpec] = {}
        self.granted: dict[tuple[int, int], int] = {}
        self._free_etag = p.FIRST_ETAG
        self.subscribers: defaultdict[int, set[int]] = defaultdict(set)  # uid -> TxNodes
        self.publishers: defaultdict[int, set[int]] = defaultdict(set)
        self.on_change: Callable[[int], None] | None = None
        self.bind_gate: Callable[[int], Awaitable[None]] | None = None
        self._gated: set[asyncio.Task[None]] = set()
        self.counters = dict.fromkeys(
            ("joined", "bound", "requests", "malformed", "foreign", "refused", "admitted"), 0
        )

    @property
    def txnodes(self) -> dict[int, int]:
        """node id -> TxNode, every assignment ever made on this bus."""
        return dict(self._store.txnodes)

    @property
    def etags(self) -> dict[int, int]:
        """channel UID -> etag, every binding ever made on this bus."""
        return dict(self._store.etags)

    def stats(self) -> dict[str, int]:
        return {
            **self.counters,
            "txnodes": len(self._store.txnodes),
            "etags": len(self._store.etags),
        }

    async def start(self) -> None:
        """Listen on the bus and say Hello, so that nodes already running announce themselves."""
        self.link.add_handler(self._handler, None)
        self.link.start()
        self._send(p.Hello(self._epoch))
        log.info(
            "CAN-ECB on %s: %d TxNodes, %d etags bound",
            self.link.channel_info,
            len(self._store.txnodes),
            len(self._store.etags),
        )

    def close(self) -> None:
        """Stop serving the bus (the link stays open). Safe to call twice."""
        if self._race_timer is not None:
            self._race_timer.cancel()
            self._race_timer = None
        for task in self._gated:
            task.cancel()
        self.link.remove_handler(self._handler)
        self._store.close()

    # --- frames ----------------------------------------------------------------------------

    def _on_frame(self, frame: can.Message) -> None:
        if not frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame:
            self.counters["foreign"] += 1
            return
        can_id = frame.arbitration_id
        if not p.is_management(can_id):
            return
        try:
            msg = p.decode(can_id, bytes(frame.data))
        except DecodeError as exc:
            self.counters["malformed"] += 1
            log.debug("skipped malformed management frame: %s", exc)
            return
        if isinstance(msg, p.Stage):
            self._on_stage(msg)
        elif isinstance(msg, p.Request):
            self.counters["requests"] += 1
            self._on_request(msg)
        elif isinstance(msg, p.Declare):
            self.counters["requests"] += 1
            self._on_declare(msg)

    # --- the TxNode race -------------------------------------------------------------------

    def _on_stage(self, msg: p.Stage) -> None:
        prefix = self._prefix
        if msg.epoch != self._epoch or msg.stage > len(prefix):
            self._announce_state()  # stale: tell the sender where the race stands
            return
        if msg.stage == len(prefix):
            prefix.append(msg.nibble)
        elif msg.nibble < prefix[msg.stage]:
            del prefix[msg.stage :]
            prefix.append(msg.nibble)
        else:  # a repeat, or a higher id than the leader's
            self._announce_state()
            return
        self._epoch = (self._epoch + 1) % p.EPOCHS
        self._send(p.Ack(self._epoch, tuple(prefix)))
        if len(prefix) < p.NIBBLES:
            self._arm_race_timer(RACE_TIMEOUT, self._restart_race)
        else:
            self._arm_race_timer(self._settle, self._complete_race)

    def _complete_race(self) -> None:
        node_id = 0
        for nib in self._prefix:
            node_id = (node_id << 4) | nib
        self._assign(node_id)
        self._restart_race()

    def _assign(self, node_id: int) -> None:
        txnode = self._store.txnodes.get(node_id)
        if txnode is None:
            taken = set(self._store.txnodes.values())
            txnode = next((t for t in range(p.TXNODE_COUNT) if t not in taken), None)
            if txnode is None:
                self.counters["refused"] += 1
                log.warning("no TxNode left for node %016x", node_id)
                self._send(p.TxNodesFull(node_id))
                return
            self._store.add_txnode(node_id, txnode)
        self.counters["joined"] += 1
        self._forget_node(txnode)  # a (re)joining node starts with no subscriptions
        log.info("node %016x has TxNode %d", node_id, txnode)
        self._send(p.Assign(txnode, node_id))

    def _restart_race(self) -> None:
        self._prefix = []
        self._epoch = (self._epoch + 1) % p.EPOCHS
        if self._race_timer is not None:
            self._race_timer.cancel()
            self._race_timer = None
        self._send(p.Reset(self._epoch))

    def _arm_race_timer(self, delay: float, then: Callable[[], None]) -> None:
        if self._race_timer is not None:
            self._race_timer.cancel()
        self._race_timer = asyncio.get_running_loop().call_later(delay, then)

    def _announce_state(self) -> None:
        if self._prefix:
            self._send(p.Ack(self._epoch, tuple(self._prefix)))
        else:
            self._send(p.Reset(self._epoch))

    # --- binding and subscriptions ---------------------------------------------------------

    def _on_request(self, msg: p.Request) -> None:
        if msg.kind == p.CLAIM:
            self._on_claim(msg.txnode, msg.value)
            return
        uid = msg.value
        if msg.kind == p.UNSUB:
            self._update(self.subscribers, uid, msg.txnode, add=False)
            return
        etag = self._etag_for(uid)
        if etag is None:
            self.counters["refused"] += 1
            self._send(p.EtagsFull(uid))
            return
        table = self.subscribers if msg.kind == p.SUB_BIND else self.publishers
        self._update(table, uid, msg.txnode, add=True)
        if msg.kind == p.PUB_BIND and self.bind_gate is not None:
            task = asyncio.get_running_loop().create_task(self._gated_bind(etag, uid))
            self._gated.add(task)
            task.add_done_callback(self._gated.discard)
        else:
            self._send(p.Bind(etag, uid))

    async def _gated_bind(self, etag: int, uid: int) -> None:
        assert self.bind_gate is not None
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(GATE_TIMEOUT):
                await self.bind_gate(uid)
        self._send(p.Bind(etag, uid))

    def _etag_for(self, uid: int) -> int | None:
        etag = self._store.etags.get(uid)
        if etag is not None:
            return etag
        taken = self._store.taken_etags
        while self._free_etag in taken:
            self._free_etag += 1
        if self._free_etag > p.LAST_ETAG:
            log.warning("no etag left for channel %016x", uid)
            return None
        self._store.add_etag(uid, self._free_etag)
        self.counters["bound"] += 1
        return self._free_etag

    def _on_claim(self, txnode: int, node_id: int) -> None:
        known = self._store.txnodes.get(node_id)
        if known == txnode:
            return
        if known is None and txnode not in self._store.txnodes.values():
            log.info("adopting TxNode %d of node %016x", txnode, node_id)
            self._store.add_txnode(node_id, txnode)
            return
        log.warning(
            "node %016x claims TxNode %d held by another node: reassigning", node_id, txnode
        )
        self._assign(node_id)  # the holder of ``txnode`` keeps it and its channels

    def _update(self, table: defaultdict[int, set[int]], uid: int, txnode: int, add: bool) -> None:
        before = len(table[uid])
        if add:
            table[uid].add(txnode)
        else:
            table[uid].discard(txnode)
        if before != len(table[uid]):
            self._changed(uid)

    def _forget_node(self, txnode: int) -> None:
        for table in (self.subscribers, self.publishers):
            for uid in [u for u, nodes in table.items() if txnode in nodes]:
                self._update(table, uid, txnode, add=False)
        for key in [k for k in self.declared if k[1] == txnode]:
            del self.declared[key]
            self.granted.pop(key, None)

    # --- real-time admission -----------------------------------------------------------------

    def _on_declare(self, msg: p.Declare) -> None:
        """Admit a stream if every declared stream of the bus stays schedulable, else refuse."""
        key = (msg.etag, msg.txnode)
        if msg.etag not in self._store.taken_etags:
            self.counters["malformed"] += 1
            log.warning("TxNode %d declared unbound etag %#x", msg.txnode, msg.etag)
            return
        unit = Fraction(p.TIME_UNIT_US, 1000)
        spec = MessageSpec(
            _stream_name(key), msg.size_bytes, msg.period * unit, msg.deadline * unit,
            msg.jitter * unit,
        )  # fmt: skip
        candidate = {**self.declared, key: spec}
        try:
            values = assign_priorities(
                [candidate[k] for k in sorted(candidate)], self.bitrate, 29,
                first=RT_FIRST, last=RT_LAST,
            )  # fmt: skip
        except NotSchedulable as exc:
            self.counters["refused"] += 1
            miss = _stream_key(exc.channel)
            response = p.RESPONSE_UNBOUNDED
            if exc.response_time_ms is not None:
                response = min(p.RESPONSE_UNBOUNDED, ceil(exc.response_time_ms * 100))
            log.info("refused %s: %s", spec.name, exc)
            self._send(p.Refuse(msg.etag, msg.txnode, miss[0], miss[1], response))
            return
        except ValueError as exc:  # more streams than priority levels
            self.counters["refused"] += 1
            log.info("refused %s: %s", spec.name, exc)
            self._send(p.Refuse(msg.etag, msg.txnode, msg.etag, msg.txnode, 0))
            return
        self.counters["admitted"] += 1
        self.declared = candidate
        for k in sorted(candidate):
            priority = values[_stream_name(k)]
            if k == key or self.granted.get(k) != priority:  # Audsley may move others
                self.granted[k] = priority
                self._send(p.Grant(k[0], k[1], priority))

    def _changed(self, uid: int) -> None:
        if self.on_change is not None:
            self.on_change(uid)

    def _send(self, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        self.link.send(can_id, data, self._handler)


async def serve(bus: str, db_path: str | Path, bitrate: int = 500_000) -> None:
    """Run a standalone CAN-ECB on ``bus`` until cancelled."""
    link = CanLink.open(bus)
    ecb = CanEcb(link, db_path, bitrate=bitrate)
    try:
        await ecb.start()
        await asyncio.Event().wait()
    finally:
        ecb.close()
        link.close()


def _stream_name(key: tuple[int, int]) -> str:
    return f"{key[0]:04x}/{key[1]}"


def _stream_key(name: str) -> tuple[int, int]:
    etag, txnode = name.split("/")
    return int(etag, 16), int(txnode)
