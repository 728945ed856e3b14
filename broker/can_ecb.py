"""The CAN Event Channel Broker: gives TxNodes to joining nodes and binds channel UIDs to etags.

Exactly one CAN-ECB serves a bus, standalone (``ups can-broker``) or hosted by the gateway.
Its tables (node id -> TxNode, UID -> etag) live in an SQLite file of the bus's own
(``_store``), so a restarted CAN-ECB gives every node and channel the same identifiers as
before. It announces an assignment or a binding only once it is durable.

A started CAN-ECB says Hello and, for ``recovery`` seconds, only listens: nodes already on the
bus claim their TxNodes and report the bindings they hold (SUB_AT, PUB_AT), and the CAN-ECB
adopts whatever does not contradict its tables. So a CAN-ECB that lost its file relearns the
bus without moving any etag. Requests for new bindings and joins wait for the window's end.

Nothing a node or a stray frame says can make two channels share an etag: a report or a Bind
that contradicts the tables is counted, logged and answered with the tables' own Binds, and
nodes re-bind on any contradiction (docs/protocol.md). A second CAN-ECB is detected by its
frames; the one that served first (else the lower instance id) stays, the other stands by.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import can

from ups import _canproto as p
from ups import _cantransfer as sizes
from ups._canlink import CanLink
from ups._errors import DecodeError

from ._admission import Admission
from ._census import Census
from ._channels import Channels
from ._store import Store, Write
from ._txnodes import TxNodes

log = logging.getLogger("ups.can_ecb")

RECOVERY = 2.0  #: seconds after Hello during which the CAN-ECB only listens and adopts (longer
#: than the nodes' Hello answer gap of 1 s, so that every node answers within it)
GATE_TIMEOUT = 1.0  #: the longest a publisher's binding waits for the gateway
HELLO_GAP = 10.0  #: at most one Hello per this many seconds for unknown TxNodes
LEASE = 86_400.0  #: a TxNode or etag unused this long may be reclaimed when none is free
MAX_CHANNELS = 8192  #: channels one TxNode may subscribe to or publish on (half the etags)
MAX_DEFERRED = 4096  #: binding requests held during the recovery window
LOG_GAP = 10.0  #: a repeated warning is logged at most this often
SERVING_GAP = 1.0  #: at most one Serving per this many seconds
STANDBY_PROBE = 2.0  #: a standing-by CAN-ECB asks this often whether the other still serves


class CanEcb:
    """The CAN-ECB of one bus.

    ``subscribers`` and ``publishers`` map each channel UID to the TxNodes that subscribe to or
    publish on it. ``on_change(uid)`` is called whenever either set of a channel changes (the
    gateway forwards by them). ``bind_gate(uid)``, when set, is awaited (at most
    ``GATE_TIMEOUT`` s) before a publisher's binding is answered, so that a gateway is
    forwarding the channel before its first event is sent. ``on_standby(reason)`` is called
    when another CAN-ECB serves the bus and this one stops answering.
    """

    def __init__(
        self,
        link: CanLink,
        db_path: str | Path,
        *,
        bitrate: int = 500_000,
        recovery: float = RECOVERY,
        lease: float = LEASE,
        max_channels: int = MAX_CHANNELS,
    ) -> None:
        self.link = link
        self._handler = self._on_frame  # one bound method, so the link can tell it apart
        self._store = Store(db_path)
        self.instance = secrets.randbits(64)
        self._recovery = recovery
        self._lease = lease
        self.recovering = False  # the tables' Phase (see _txnodes): in a recovery window
        self.standby = False  # another CAN-ECB serves the bus
        self._admission = Admission(bitrate, fd=link.fd)
        self.bitrate = bitrate
        self._uid_at = {e: u for u, e in self._store.etags.items()}  # etag -> UID
        #: uid -> the etag being stored for it, and the (kind, TxNode, size class) waiting for it
        self._pending_etag: dict[int, tuple[int, list[tuple[int, int, int]]]] = {}
        self._pending_etags: set[int] = set()  # the etags of _pending_etag
        #: size class -> no etag of that class below it is free
        self._free_from = [sizes.class_etags(c).start for c in range(p.SIZE_CLASSES)]
        now = time.monotonic()
        self._seen_etag: dict[int, float] = {}  # etag -> last event (default: start time)
        self._started = now
        self._deferred: dict[tuple[int, int, int, int], None] = {}
        self._knocked = False
        self._recovery_timer: asyncio.TimerHandle | None = None
        self._last_unknown_hello = -HELLO_GAP  # the last Hello sent for an unknown TxNode
        self.strays: set[int] = set()  # TxNodes heard asking while unknown, since that Hello
        self.started_up = False  # the first recovery (after start) is over
        self._logged: dict[str, float] = {}
        self._last_serving = -1.0
        self._other_heard = 0.0  # in standby: when the serving CAN-ECB was last heard
        self._probe_timer: asyncio.TimerHandle | None = None
        self.on_change: Callable[[int], None] | None = None
        self.bind_gate: Callable[[int], Awaitable[None]] | None = None
        self.on_standby: Callable[[str], None] | None = None
        self._gated: set[asyncio.Task[None]] = set()
        self.counters = dict.fromkeys(
            (
                "joined", "bound", "requests", "malformed", "foreign", "refused", "admitted",
                "adopted", "conflicts", "foreign_ecb_frames", "unassigned", "deferred",
                "limited", "reclaimed", "storage_errors", "handler_errors", "offers_withdrawn",
                "moved",
            ),
            0,
        )  # fmt: skip
        self._txnodes = TxNodes(
            self._store, phase=self, send=self._send, counters=self.counters, warn=self._warn,
            stored=self._stored, log_failure=self._log_failure, forget=self._forget_node,
            unassigned=self._unassigned, lease=lease,
        )  # fmt: skip
        self._census = Census(self._send, self._txnodes.found)
        self._channels = Channels(
            max_channels, send=self._send, counters=self.counters, warn=self._warn,
            changed=self._changed,
        )  # fmt: skip
        self.subscribers = self._channels.subscribers  # uid -> TxNodes
        self.publishers = self._channels.publishers

    # --- tables and statistics -------------------------------------------------------------

    @property
    def txnodes(self) -> dict[int, int]:
        """node id -> TxNode, every durable assignment on this bus."""
        return dict(self._store.txnodes)

    @property
    def etags(self) -> dict[int, int]:
        """channel UID -> etag, every durable binding on this bus."""
        return dict(self._store.etags)

    @property
    def declared(self) -> dict[tuple[int, int], object]:
        return dict(self._admission.declared)

    @property
    def granted(self) -> dict[tuple[int, int], int]:
        return dict(self._admission.granted)

    @property
    def healthy(self) -> bool:
        """False while the database fails or another CAN-ECB serves the bus."""
        return self._store.last_error is None and not self.standby

    def stats(self) -> dict[str, object]:
        return {
            **self.counters,
            **{f"census_{k}": v for k, v in self._census.counters.items()},
            "txnodes": len(self._store.txnodes),
            "etags": len(self._store.etags),
            "storage_batches": self._store.batches,
            "storage_error": self._store.last_error,
            "db": str(self._store.path),
            "healthy": self.healthy,
            "standby": self.standby,
            "instance": f"{self.instance:016x}",
        }

    def status(self) -> dict[str, Any]:
        """The tables as ``ups status`` and ``ups ls`` show them: nodes, and each channel's
        etag, publishing and subscribing TxNodes (hex); the counters under ``stats``."""
        txnode_of = self._store.txnodes
        return {
            "nodes": [{"node_id": f"0x{n:016x}", "txnode": f"0x{t:02x}"}
                      for n, t in sorted(txnode_of.items(), key=lambda i: i[1])],
            "channels": [
                {"uid": f"0x{u:016x}", "etag": f"0x{e:04x}",
                 "publishers": [f"0x{t:02x}" for t in sorted(self.publishers.get(u, ()))],
                 "subscribers": [f"0x{t:02x}" for t in sorted(self.subscribers.get(u, ()))]}
                for u, e in sorted(self._store.etags.items(), key=lambda i: i[1])
            ],
            "stats": self.stats(),
        }  # fmt: skip

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        """Listen on the bus and say Hello, so that nodes already running announce themselves."""
        self._store.start()
        self.link.add_handler(self._handler, None)
        self.link.start()
        self._hello()
        log.info(
            "CAN-ECB on %s: %d TxNodes, %d etags bound (%s), instance %016x",
            self.link.channel_info,
            len(self._store.txnodes),
            len(self._store.etags),
            self._store.path,
            self.instance,
        )

    def close(self) -> None:
        """Stop serving the bus (the link stays open). Safe to call twice."""
        self._census.close()
        self._txnodes.close()
        for timer in (self._recovery_timer, self._probe_timer):
            if timer is not None:
                timer.cancel()
        self._recovery_timer = None
        self._probe_timer = None
        for task in self._gated:
            task.cancel()
        self.link.remove_handler(self._handler)
        self._store.close()

    def _hello(self) -> None:
        """Say Hello and listen for ``recovery`` s (at start, and when the tables are behind)."""
        self.recovering = True
        if self._recovery_timer is not None:
            self._recovery_timer.cancel()
        loop = asyncio.get_running_loop()
        self._recovery_timer = loop.call_later(self._recovery, self._recovered)
        self._send(p.Hello(self.instance))

    def _recovered(self) -> None:
        self._recovery_timer = None
        self.recovering = False
        self.strays.clear()
        if self.standby:
            return
        self.started_up = True
        deferred, self._deferred = list(self._deferred), {}
        for kind, txnode, uid, size_class in deferred:
            self._on_bind_request(p.Request(kind, txnode, uid, size_class))
        if self._knocked:
            self._knocked = False
            self._census.knock()

    # --- frames ----------------------------------------------------------------------------

    def _on_frame(self, frame: can.Message) -> None:
        if not frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame:
            self.counters["foreign"] += 1
            return
        can_id = frame.arbitration_id
        if frame.is_fd and p.is_management(can_id):  # management frames are classic frames
            self.counters["foreign"] += 1
            return
        txnode = (can_id >> p.TXNODE_SHIFT) & p.TXNODE_MASK
        now = time.monotonic()
        if txnode != p.MGMT_TXNODE:
            self._txnodes.seen[txnode] = now
        if not p.is_management(can_id):
            self._seen_etag[can_id & p.ETAG_MASK] = now
            return
        try:
            msg = p.decode(can_id, bytes(frame.data))
        except DecodeError as exc:
            self.counters["malformed"] += 1
            log.debug("skipped malformed management frame: %s", exc)
            return
        try:
            self._on_management(msg)
        except Exception:  # a bug must not stop the CAN-ECB: count it, log it, go on
            self.counters["handler_errors"] += 1
            log.exception("CAN-ECB failed on %s", msg)

    def _on_management(self, msg: p.Management) -> None:
        if isinstance(msg, p.ECB_FRAMES):
            self._on_foreign_ecb(msg)
        elif self.standby:
            return
        elif isinstance(msg, p.Stage):
            if not self.recovering:
                self._census.on_stage(msg)
        elif isinstance(msg, p.Knock):
            if self.recovering:
                self._knocked = True
            else:
                self._census.knock()
        elif isinstance(msg, p.Request | p.Holds | p.Declare):
            self.counters["requests"] += 1
            if isinstance(msg, p.Request) and msg.kind == p.CLAIM:
                self._txnodes.on_claim(msg.txnode, msg.value)
            elif msg.txnode not in self._txnodes.node_at:
                self._unassigned(msg.txnode)
            elif isinstance(msg, p.Holds):
                self._on_holds(msg)
            elif isinstance(msg, p.Declare):
                self._on_declare(msg)
            elif msg.kind == p.UNSUB:
                self._channels.unsubscribe(msg.value, msg.txnode)
            else:
                self._on_bind_request(msg)

    def _unassigned(self, txnode: int) -> None:
        """A request from a TxNode this CAN-ECB does not know: its tables are behind the bus
        (or someone forges frames). Say Hello again, so that nodes claim (rate-limited)."""
        self.counters["unassigned"] += 1
        self._warn("unassigned", "request from TxNode 0x%02x, which no node holds", txnode)
        self.strays.add(txnode)
        if not self.recovering and time.monotonic() - self._last_unknown_hello >= HELLO_GAP:
            self._last_unknown_hello = time.monotonic()
            self._hello()

    # --- another CAN-ECB, or forged frames ---------------------------------------------------

    def _on_foreign_ecb(self, msg: p.Management) -> None:
        self.counters["foreign_ecb_frames"] += 1
        if self.standby:
            if isinstance(msg, p.Hello | p.Serving) and msg.instance != self.instance:
                self._other_heard = time.monotonic()  # the one serving is still there
            return
        if isinstance(msg, p.Hello | p.Serving):
            if msg.instance == self.instance:
                return
            first = isinstance(msg, p.Serving) and self.recovering
            if first or (
                (self.recovering or isinstance(msg, p.Serving)) and msg.instance < self.instance
            ):
                self._stand_by(f"CAN-ECB {msg.instance:016x} already serves this bus")
                return
            self._warn("ecb", "another CAN-ECB (%016x) on this bus: telling it to stand by",
                       msg.instance)  # fmt: skip
            self._serving()
            return
        if isinstance(msg, p.Bind) and self._uid_at.get(msg.etag) != msg.uid:
            self.counters["conflicts"] += 1
            self._warn("bind", "a Bind(%#x, %016x) that this CAN-ECB did not send: correcting",
                       msg.etag, msg.uid)  # fmt: skip
            self._correct(msg.etag, msg.uid)
        elif isinstance(msg, p.Assign) and self._store.txnodes.get(msg.node_id) not in (
            None, msg.txnode,
        ):  # fmt: skip
            self.counters["conflicts"] += 1  # a node told to move where its table does not say
            self._warn("assign", "an Assign(%d, %016x) that this CAN-ECB did not send: "
                       "correcting", msg.txnode, msg.node_id)  # fmt: skip
            self._send(p.Assign(self._store.txnodes[msg.node_id], msg.node_id))
        else:
            self._warn("ecb", "a %s that this CAN-ECB did not send: another CAN-ECB or a "
                       "forger", type(msg).__name__)  # fmt: skip
        self._serving()

    def _serving(self) -> None:
        """Tell whoever sends CAN-ECB frames that this one serves the bus (at most 1/s)."""
        now = time.monotonic()
        if now - self._last_serving >= SERVING_GAP:
            self._last_serving = now
            self._send(p.Serving(self.instance))

    def _stand_by(self, reason: str) -> None:
        """Another CAN-ECB serves the bus: answer nothing, but check now and then that it is
        still there (it answers our Serving with its own); take over when it is not."""
        self.standby = True
        self._census.close()
        self._other_heard = time.monotonic()
        log.error("%s: this CAN-ECB stands by and answers nothing", reason)
        if self.on_standby is not None:
            self.on_standby(reason)
        self._probe_timer = asyncio.get_running_loop().call_later(STANDBY_PROBE, self._probe)

    def _probe(self) -> None:
        self._probe_timer = None
        if not self.standby:
            return
        if time.monotonic() - self._other_heard > 2 * STANDBY_PROBE:
            log.warning("the other CAN-ECB is silent: this one serves the bus again")
            self.standby = False
            self.started_up = False  # it heard nothing while standing by: learn the bus anew
            self._hello()
            return
        self._send(p.Serving(self.instance))  # a CAN-ECB that serves answers with its own
        self._probe_timer = asyncio.get_running_loop().call_later(STANDBY_PROBE, self._probe)

    def _correct(self, etag: int, uid: int) -> None:
        """Repeat the tables' truth about ``etag`` and ``uid``."""
        if etag in self._uid_at:
            self._send(p.Bind(etag, self._uid_at[etag]))
        if uid in self._store.etags and self._store.etags[uid] != etag:
            self._send(p.Bind(self._store.etags[uid], uid))

    def _log_failure(self, what: str) -> Callable[[BaseException | None], None]:
        """A write's callback when nobody waits for it: a failure is only counted and logged."""

        def done(error: BaseException | None) -> None:
            self._stored(error, what, None)

        return done

    # --- binding and subscriptions -------------------------------------------------------------

    def _on_bind_request(self, msg: p.Request) -> None:
        """Bind ``uid`` to an etag of at least the asked size class: the one it has, or a new
        one (a channel that needs a larger class moves; its nodes see the contradiction and
        bind it again)."""
        uid, txnode, size_class = msg.value, msg.txnode, msg.size_class
        etag = self._store.etags.get(uid)
        fits = etag is not None and sizes.size_class(etag) >= size_class
        if self.recovering and not fits:
            if len(self._deferred) < MAX_DEFERRED:
                self.counters["deferred"] += 1
                self._deferred[(msg.kind, txnode, uid, size_class)] = None
            return
        if not self._channels.within_limit(txnode, uid):
            return
        if etag is not None and fits:
            self._bound(msg.kind, txnode, uid, etag)
            return
        pending = self._pending_etag.get(uid)
        if pending is not None:
            pending[1].append((msg.kind, txnode, size_class))
            self._channels.ask(txnode, uid)
            return
        writes: list[Write] = []
        etag = self._free_etag(writes, size_class)
        if etag is None:
            self.counters["refused"] += 1
            self._warn("etags", "no etag of size class %d left for channel %016x", size_class,
                       uid)  # fmt: skip
            self._send(p.EtagsFull(uid))
            return
        if uid in self._store.etags:
            self.counters["moved"] += 1
            log.info("channel %016x moves to etag %#x (size class %d)", uid, etag, size_class)
        self._pending_etag[uid] = (etag, [(msg.kind, txnode, size_class)])
        self._pending_etags.add(etag)
        self._channels.ask(txnode, uid)
        writes.append(("etags", uid, etag))
        self._store.submit(writes, self._bind_done(uid, etag))

    def _bind_done(self, uid: int, etag: int) -> Callable[[BaseException | None], None]:
        def done(error: BaseException | None) -> None:
            _, asks = self._pending_etag.pop(uid)
            self._pending_etags.discard(etag)
            for _, txnode, _ in asks:
                self._channels.answered(txnode, uid)
            if not self._stored(error, f"etag {etag:#x} of channel {uid:016x}", uid):
                cls = sizes.size_class(etag)
                self._free_from[cls] = min(self._free_from[cls], etag)
                return
            self.counters["bound"] += 1
            self._hold_etag(uid, etag)
            for kind, txnode, size_class in asks:
                if txnode not in self._txnodes.node_at:
                    continue
                if sizes.size_class(etag) >= size_class:
                    self._bound(kind, txnode, uid, etag)
                else:  # asked for more while a smaller etag was being stored
                    self._on_bind_request(p.Request(kind, txnode, uid, size_class))

        return done

    def _bound(self, kind: int, txnode: int, uid: int, etag: int) -> None:
        publish = kind == p.PUB_BIND
        self._channels.use(publish, uid, txnode)
        if publish and self.bind_gate is not None:
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

    def _free_etag(self, writes: list[Write], size_class: int) -> int | None:
        pending = self._pending_etags
        etags = sizes.class_etags(size_class)
        etag = self._free_from[size_class]  # no etag of the class below it is free
        while etag < etags.stop and (etag in self._uid_at or etag in pending):
            etag += 1
        self._free_from[size_class] = etag
        if etag < etags.stop:
            return etag
        now = time.monotonic()
        idle = [
            e for e, u in self._uid_at.items()
            if e in etags and e not in pending and not self.subscribers.get(u)
            and not self.publishers.get(u)
        ]  # fmt: skip
        oldest = min(idle, key=lambda e: self._seen_etag.get(e, self._started), default=None)
        if oldest is None or now - self._seen_etag.get(oldest, self._started) < self._lease:
            return None
        old_uid = self._uid_at.pop(oldest)
        del self._store.etags[old_uid]
        writes.append(("etags", old_uid, None))
        self.counters["reclaimed"] += 1
        log.warning("reclaimed etag %#x of channel %016x, unused", oldest, old_uid)
        return oldest

    def _hold_etag(self, uid: int, etag: int) -> None:
        old = self._store.etags.get(uid)
        if old is not None and old != etag:  # the channel moved to a larger size class
            del self._uid_at[old]
            cls = sizes.size_class(old)
            self._free_from[cls] = min(self._free_from[cls], old)
            self._admission.forget_etag(old)
        self._store.etags[uid] = etag
        self._uid_at[etag] = uid

    def _on_holds(self, msg: p.Holds) -> None:
        """A node reports a binding it holds (SUB_AT / PUB_AT)."""
        uid, etag = msg.uid, msg.etag
        known = self._store.etags.get(uid)
        holder = self._uid_at.get(etag)
        kind = p.PUB_BIND if msg.publish else p.SUB_BIND
        if known == etag:
            if self._channels.within_limit(msg.txnode, uid):
                self._channels.use(msg.publish, uid, msg.txnode)
            return
        if (
            known is None
            and holder is None
            and etag not in self._pending_etags
            and uid not in self._pending_etag
        ):
            if not self._channels.within_limit(msg.txnode, uid):
                return
            self.counters["adopted"] += 1
            log.info("adopting etag %#x of channel %016x from TxNode 0x%02x", etag, uid, msg.txnode)
            self._hold_etag(uid, etag)
            self._store.submit([("etags", uid, etag)], self._log_failure(f"adopted etag {etag:#x}"))
            self._channels.use(msg.publish, uid, msg.txnode)
            return
        self.counters["conflicts"] += 1
        self._warn("holds", "TxNode 0x%02x holds %016x at etag %#x, which contradicts the tables: "
                   "correcting", msg.txnode, uid, etag)  # fmt: skip
        self._correct(etag, uid)
        if known is None and not self.recovering:  # it will ask again; answer it now
            self._on_bind_request(p.Request(kind, msg.txnode, uid))

    def _forget_node(self, txnode: int) -> None:
        self._channels.forget(txnode)
        self._admission.forget(txnode)

    # --- real-time admission -------------------------------------------------------------------

    def _on_declare(self, msg: p.Declare) -> None:
        """Admit a stream if every declared stream of the bus stays schedulable, else refuse."""
        uid = self._uid_at.get(msg.etag)
        if uid is None or msg.txnode not in self.publishers.get(uid, ()):
            self.counters["malformed"] += 1
            self._warn("declare-unbound", "TxNode 0x%02x declared etag %#x, which it does not "
                       "publish on", msg.txnode, msg.etag)  # fmt: skip
            return
        repeat = self._admission.repeat(msg)
        if repeat is not None:
            self._send(repeat)
            return
        if not self._admission.within_rate(msg.txnode):
            self.counters["limited"] += 1
            self._warn("declare", "TxNode 0x%02x declares too often: ignored", msg.txnode)
            return
        verdict = self._admission.decide(msg)
        self.counters["admitted" if verdict.admitted else "refused"] += 1
        for frame in verdict.frames:
            self._send(frame)

    # --- helpers -------------------------------------------------------------------------------

    def _stored(self, error: BaseException | None, what: str, value: int | None) -> bool:
        """Report a write's outcome; on failure tell the asker (Failed) and count it."""
        if error is None:
            return True
        self.counters["storage_errors"] += 1
        log.error("CAN-ECB could not store %s in %s: %s", what, self._store.path, error)
        if value is not None:
            self._send(p.Failed(value))
        return False

    def _warn(self, key: str, text: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._logged.get(key, -LOG_GAP) >= LOG_GAP:
            self._logged[key] = now
            log.warning(text, *args)

    def _changed(self, uid: int) -> None:
        if self.on_change is not None:
            self.on_change(uid)

    def _send(self, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        self.link.send(can_id, data, self._handler)


async def serve(
    bus: str, db_path: str | Path, bitrate: int = 500_000, status: str | None = None,
    **options: float | int,
) -> int:  # fmt: skip
    """Run a standalone CAN-ECB on ``bus`` until cancelled; with ``status`` (HOST:PORT) its
    tables are served there to ``ups status`` and ``ups ls --can ... --ecb``.

    Returns 1 if the database failed during the run, else 0. Standing by for another CAN-ECB
    is logged; it serves again when the other goes silent.
    """
    from ._status import StatusServer

    link = CanLink.open(bus)
    try:
        ecb = CanEcb(link, db_path, bitrate=bitrate, **options)  # type: ignore[arg-type]
    except BaseException:
        link.close()
        raise
    server = None if status is None else StatusServer(status, ecb.status)
    try:
        if server is not None:
            await server.start()
        await ecb.start()
        await asyncio.Event().wait()
        return 0
    except asyncio.CancelledError:
        return 1 if ecb.counters["storage_errors"] else 0
    finally:
        if server is not None:
            await server.close()
        ecb.close()
        link.close()
