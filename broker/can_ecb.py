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
frames; which one serves and which stands by is the election's (``_election``): the one that
served first stays (of two candidates, the lower instance), and a standing-by one takes over
when the one that serves goes silent, or leaves a request it hears unanswered (a Serving alone
is a claim anyone can forge).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import can

from ups import _canproto as p
from ups._canlink import CanLink
from ups._errors import DecodeError

from ._admission import Admission
from ._census import Census
from ._channels import Channels
from ._election import Election, Role
from ._etags import Etags
from ._forged import Corrections
from ._quota import QUOTA, Quota
from ._roster import Rosters
from ._store import Store
from ._txnodes import TxNodes

log = logging.getLogger("ups.can_ecb")

RECOVERY = 2.0  #: seconds after Hello during which the CAN-ECB only listens and adopts (longer
#: than the nodes' Hello answer gap of 1 s, so that every node answers within it)
HELLO_GAP = 10.0  #: at most one Hello per this many seconds for unknown TxNodes
LEASE = 86_400.0  #: a TxNode or etag unused this long may be reclaimed when none is free
MAX_CHANNELS = 8192  #: channels one TxNode may subscribe to or publish on (half the etags)
LOG_GAP = 10.0  #: a repeated warning is logged at most this often


class CanEcb:
    """The CAN-ECB of one bus.

    ``subscribers`` and ``publishers`` map each channel UID to the TxNodes that subscribe to or
    publish on it. ``on_change(uid)`` is called whenever either set of a channel changes (the
    gateway forwards by them). ``bind_gate(uid, txnode)``, when set, is awaited (at most
    ``_etags.GATE_TIMEOUT`` s) before the binding of publisher ``txnode`` is answered, so that a
    gateway is forwarding the channel before its first event is sent. ``on_standby(reason)`` is
    called when another CAN-ECB serves the bus and this one stops answering, ``on_serving()``
    whenever it serves with whole tables (a recovery window ended, not standing by).
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
        quota: tuple[int, int, int, int, int] = QUOTA,
    ) -> None:
        self.link = link
        self._handler = self._on_frame  # one bound method, so the link can tell it apart
        self._store = Store(db_path)
        self.instance = secrets.randbits(64)
        self._recovery = recovery
        self.recovering = False  # the tables' Phase (see _txnodes): in a recovery window
        self.standby = False  # another CAN-ECB serves the bus
        self._admission = Admission(bitrate, fd=link.fd)
        self.bitrate = bitrate
        self._knocked = False
        self._recovery_timer: asyncio.TimerHandle | None = None
        self._last_unknown_hello = -HELLO_GAP  # the last Hello sent for an unknown TxNode
        self.strays: set[int] = set()  # TxNodes heard asking while unknown, since that Hello
        self.started_up = False  # the first recovery (after start) is over
        self._logged: dict[str, float] = {}
        self._election = Election(self.instance, recovery)
        self._election_timer: asyncio.TimerHandle | None = None
        self.on_change: Callable[[int], None] | None = None
        self.on_standby: Callable[[str], None] | None = None
        self.on_serving: Callable[[], None] | None = None
        self.counters = dict.fromkeys(
            (
                "joined", "bound", "requests", "malformed", "foreign", "refused", "admitted",
                "adopted", "conflicts", "foreign_ecb_frames", "unassigned", "deferred",
                "limited", "reclaimed", "storage_errors", "handler_errors", "offers_withdrawn",
                "moved", "late_claims", "quota_hit",
            ),
            0,
        )  # fmt: skip
        self._txnodes = TxNodes(
            self._store, phase=self, send=self._send, counters=self.counters, warn=self._warn,
            stored=self._stored, log_failure=self._log_failure, forget=self._forget_node,
            unassigned=self._unassigned, lease=lease, offer_wait=lambda: 2 * self._census.slack,
        )  # fmt: skip
        self._census = Census(self._send, self._txnodes.found)
        self._channels = Channels(
            max_channels, send=self._send, counters=self.counters, warn=self._warn,
            changed=self._changed,
        )  # fmt: skip
        self.subscribers = self._channels.subscribers  # uid -> TxNodes
        self.publishers = self._channels.publishers
        self._etags = Etags(
            self._store, phase=self, channels=self._channels, admission=self._admission,
            assigned=self._txnodes.node_at, send=self._send, counters=self.counters,
            quota=Quota(quota, self._store.creators, self._store.etags),
            warn=self._warn, stored=self._stored, log_failure=self._log_failure, lease=lease,
        )  # fmt: skip
        self._rosters = Rosters(
            self.subscribers, self.publishers, send=self._send, counters=self.counters,
            recovering=lambda: self.recovering,
        )  # fmt: skip
        self._corrections = Corrections(
            etags=self._etags, txnodes=self._txnodes, admission=self._admission,
            send=self._send, counters=self.counters, warn=self._warn,
        )  # fmt: skip

    # --- tables and statistics -------------------------------------------------------------

    @property
    def bind_gate(self) -> Callable[[int, int], Awaitable[None]] | None:
        return self._etags.gate

    @bind_gate.setter
    def bind_gate(self, gate: Callable[[int, int], Awaitable[None]] | None) -> None:
        self._etags.gate = gate

    @property
    def txnodes(self) -> dict[int, int]:
        """node id -> TxNode, every durable assignment on this bus."""
        return dict(self._store.txnodes)

    @property
    def etags(self) -> dict[int, int]:
        """channel UID -> etag, every durable binding on this bus."""
        return dict(self._store.etags)

    @property
    def creators(self) -> dict[int, int]:
        """channel UID -> the node id that created its binding (its quota's count)."""
        return dict(self._store.creators)

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
            "unanswered_takeovers": self._election.unanswered,
            **{f"census_{k}": v for k, v in self._census.counters.items()},
            "txnodes": len(self._store.txnodes),
            "etags": len(self._store.etags),
            "storage_batches": self._store.batches,
            "storage_error": self._store.last_error,
            "db": str(self._store.path),
            "healthy": self.healthy,
            "standby": self.standby,
            "role": self._election.role.value,
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
        self._elect(self._election.start(asyncio.get_running_loop().time()))
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
        self._rosters.close()
        for timer in (self._recovery_timer, self._election_timer):
            if timer is not None:
                timer.cancel()
        self._recovery_timer = None
        self._election_timer = None
        self._etags.close()
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
        self._etags.replay()
        self._rosters.pump()  # the tables are whole again: rosters asked meanwhile
        if self.on_serving is not None:
            self.on_serving()
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
        if txnode != p.MGMT_TXNODE:  # before it is handled: an adopting CLAIM stays on probation
            self._txnodes.heard(txnode, now)
        if not p.is_management(can_id):
            self._etags.seen[can_id & p.ETAG_MASK] = now
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
        elif self.standby:  # answers nothing, but watches that the one serving does
            held = isinstance(msg, p.Request) and msg.txnode in self._txnodes.node_at
            self._elect(self._election.asked(msg, asyncio.get_running_loop().time(), held))
        elif isinstance(msg, p.Stage):
            if not self.recovering:
                self._census.on_stage(msg)
        elif isinstance(msg, p.Knock):
            if self.recovering:
                self._knocked = True
            else:
                self._census.knock()
        elif isinstance(msg, p.Request | p.Holds | p.Declare | p.Roster):
            self.counters["requests"] += 1
            if isinstance(msg, p.Request) and msg.kind == p.CLAIM:
                self._txnodes.on_claim(msg.txnode, msg.value)
            elif msg.txnode not in self._txnodes.node_at:
                self._unassigned(msg.txnode)
            elif isinstance(msg, p.Roster):
                self._rosters.ask(msg)
            elif isinstance(msg, p.Holds):
                self._etags.on_holds(msg)
            elif isinstance(msg, p.Declare):
                self._on_declare(msg)
            elif msg.kind == p.UNSUB:
                self._etags.unsubscribed(msg.value, msg.txnode)
                self._channels.unsubscribe(msg.value, msg.txnode)
            else:
                self._etags.on_request(msg)

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
        """A CAN-ECB frame this one did not send: correct what contradicts its tables, and let
        the election answer (Serving) or stand this one by."""
        self.counters["foreign_ecb_frames"] += 1
        if not self.standby:
            self._correct(msg)
        busy = self.recovering or self._census.running  # standing by would drop what it holds
        self._elect(self._election.heard(msg, asyncio.get_running_loop().time(), busy))

    def _correct(self, msg: p.Management) -> None:
        if isinstance(msg, p.Hello | p.Serving | p.Probe):
            if msg.instance != self.instance:
                self._warn("ecb", "another CAN-ECB (%016x) on this bus: %s", msg.instance,
                           type(msg).__name__)  # fmt: skip
        else:
            self._corrections.correct(msg)

    def _elect(self, frames: list[p.Hello | p.Serving | p.Probe]) -> None:
        """Carry out what the election decided: a change of role, its frames, its next timer."""
        role = self._election.role
        if role is Role.STANDBY and not self.standby:
            self.standby = True  # answer nothing, but probe now and then (the election's)
            self._census.close()
            self._rosters.close()
            reason = self._election.reason
            log.error("%s: this CAN-ECB stands by and answers nothing", reason)
            if self.on_standby is not None:
                self.on_standby(reason)
        elif role is not Role.STANDBY and self.standby:
            wary = ", and stands by only for one it hears answer" * self._election.wary
            log.warning("%s: this one serves the bus again%s", self._election.reason, wary)
            self.standby = False
            self.started_up = False  # it heard nothing while standing by: learn the bus anew
        for frame in frames:
            if isinstance(frame, p.Hello):
                self._hello()  # and a recovery window (the candidacy ends with it, or sooner)
            else:
                self._send(frame)
        deadline = self._election.deadline
        timer = self._election_timer
        if timer is not None and timer.when() == deadline:
            return
        if timer is not None:
            timer.cancel()
        self._election_timer = None
        if deadline is not None:
            self._election_timer = asyncio.get_running_loop().call_at(
                deadline, self._election_due, deadline
            )

    def _election_due(self, deadline: float) -> None:
        self._election_timer = None
        now = max(asyncio.get_running_loop().time(), deadline)  # a timer may fire a bit early
        self._elect(self._election.tick(now))

    def _log_failure(self, what: str) -> Callable[[BaseException | None], None]:
        """A write's callback when nobody waits for it: a failure is only counted and logged."""

        def done(error: BaseException | None) -> None:
            self._stored(error, what, None)

        return done

    def _forget_node(self, txnode: int) -> None:
        self._channels.forget(txnode)
        self._admission.forget(txnode)

    # --- real-time admission -------------------------------------------------------------------

    def _on_declare(self, msg: p.Declare) -> None:
        """Admit a stream if every declared stream of the bus stays schedulable, else refuse."""
        uid = self._etags.uid_at.get(msg.etag)
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
    metrics: str | None = None, **options: float | int,
) -> int:  # fmt: skip
    """Run a standalone CAN-ECB on ``bus`` until cancelled; with ``status`` (HOST:PORT) its
    tables are served there to ``ups status`` and ``ups ls --can ... --ecb``; with ``metrics``
    (HOST:PORT) its counters, to Prometheus.

    Returns 1 if the database failed during the run, else 0. Standing by for another CAN-ECB
    is logged; it serves again when the other goes silent.
    """
    from ._serving import run

    def make(link: CanLink) -> CanEcb:
        return CanEcb(link, db_path, bitrate=bitrate, **options)  # type: ignore[arg-type]

    ecb = await run(bus, make, "can-broker", status, metrics)
    return 1 if ecb.counters["storage_errors"] else 0
