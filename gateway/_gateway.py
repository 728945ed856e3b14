"""The gateway: one ECH with a CAN face and an IP face (TCP/IP or Zenoh), forwarding only what
is subscribed.

As in section 4.3 of the paper (where the IP side is TCP/IP; on Zenoh, the same with Zenoh's
matching subscribers in place of the TCP-ECB's lists):

- TCP -> CAN, for a channel that some CAN node subscribes to. The gateway subscribes on the
  TCP side on the CAN nodes' behalf, and withdraws when the last of them leaves.
- CAN -> TCP, for a channel that some CAN node publishes on and some TCP node subscribes to.
  The gateway advertises on the TCP side every channel published on its bus, and so learns
  who subscribes.

An event is never sent back into the network it came from: what arrives from TCP goes only to
CAN, and what arrives from CAN goes only to TCP. The gateway's own CAN frames come back to it
as echoes, which the CAN face discards. The priority of every event is kept across the hop.

What the bus cannot carry is not pushed at it. TCP->CAN events wait in a queue of
``can_queue`` events, which is drained no faster than ``bitrate`` allows (worst-case stuffed
frame lengths, every frame of an event larger than one frame). When the queue is full the
oldest event is dropped, and counted. An event larger than its channel's size class on the
bus moves the channel to a larger class first (see ``CanFace.grow``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from ups._canlink import CanLink
from ups._catalog import Catalog
from ups._errors import AccessDenied, ConfigError
from ups._face import ChannelState
from ups._message import Message
from ups._node import Node
from ups._nodeid import claim_node_id
from ups._tls import Tls
from ups.broker._store import default_db
from ups.broker.can_ecb import RECOVERY, CanEcb

from ._backlog import RECONCILERS, Backlog
from ._pacer import Pacer
from ._tables import Tables
from ._tap import Tap

log = logging.getLogger("ups.gateway")

CLOSE_TRIES = 5  # times close() cancels a task (a second apart) before it gives up on it


class _Forward:
    """A sink in one side's channel table: hands each event to the gateway for the other side,
    with ``state``, the other side's state of the channel."""

    def __init__(self, send: Callable[[ChannelState, Message], None], state: ChannelState) -> None:
        self._send = send
        self.state = state

    def _push(self, msg: Message) -> None:
        self._send(self.state, msg)


class Gateway:
    """A gateway between the CAN bus ``can`` and the TCP/IP network of the TCP-ECB ``broker``,
    or the Zenoh network of the router at ``zenoh`` (with ``zenoh_config``, a Zenoh config file).

    By default it hosts the bus's CAN-ECB, its tables in the SQLite file ``db`` (by default the
    bus's own file, ``broker._store.default_db``, the same a standalone CAN-ECB would use);
    ``host_can_ecb=False`` uses a CAN-ECB that already serves the bus. In that case the gateway
    learns who subscribes and publishes from the nodes' requests and from the serving CAN-ECB's
    roster (``_tables``). ``catalog`` names the bus's channels on the IP side (pattern
    subscriptions there match names). ``bitrate`` is the
    bus's bit rate (admission control, pacing). ``recovery`` is the hosted CAN-ECB's recovery
    window after its Hello (``CanEcb``'s; shorter only where no node can be on the bus before
    the gateway, as in the demo's own virtual bus). ``listen`` is where TCP publishers reach it
    (and ``ups status`` too).
    """

    def __init__(
        self,
        can: str | CanLink,
        broker: str | None = None,
        *,
        zenoh: str | None = None,
        zenoh_config: str | Path | None = None,
        db: str | Path | None = None,
        host_can_ecb: bool = True,
        bitrate: int = 500_000,
        recovery: float = RECOVERY,
        node_id: int | None = None,
        name: str = "ups-gateway",
        listen: str | None = None,
        join_timeout: float | None = 30.0,
        can_queue: int = 256,
        tls: Tls | None = None,
        catalog: Catalog | None = None,
    ) -> None:
        if can_queue < 1:
            raise ConfigError(f"can_queue must be at least 1, got {can_queue}")
        if bitrate <= 0:
            raise ConfigError(f"bitrate must be positive, got {bitrate}")
        if (broker is None) == (zenoh is None and zenoh_config is None):
            raise ConfigError("a gateway joins one IP network: broker='HOST:PORT' or zenoh=...")
        if tls is not None and broker is None:
            raise ConfigError("tls= is for the TCP/IP side; on Zenoh, TLS is in its config")
        if broker is None:  # before anything opens: say so now when Zenoh is not installed
            from ups._zenohface import require_zenoh

            require_zenoh()
        self._can_spec = can
        self._tls = tls
        #: names of the bus's channels (CAN nodes send none): registered with them on the IP
        #: side, so that the TCP-ECB and Zenoh match them against pattern subscriptions
        self._catalog = catalog or Catalog()
        #: the IP side: ("broker", HOST:PORT) or ("zenoh", ENDPOINT)
        self._ip_network = ("broker", broker) if broker is not None else ("zenoh", zenoh or "")
        self._zenoh_config = zenoh_config
        self.side = "tcp" if broker is not None else "zenoh"  #: the IP side, in counters
        self._to_ip_counter = f"to_{self.side}"
        self._db = db
        self._host_can_ecb = host_can_ecb
        self.bitrate = bitrate
        self._recovery = recovery
        self._node_id = node_id
        self.name = name
        self._listen = listen
        self._join_timeout = join_timeout
        self._can_queue = can_queue
        self._pacer: Pacer | None = None  #: TCP->CAN, paced to the bit rate
        self._link: CanLink | None = None
        self._owns_link = False
        self._ecb: CanEcb | None = None
        #: who uses what on the bus, learnt from the nodes' requests and the CAN-ECB's roster:
        #: the tables forwarded by when there is no hosted CAN-ECB, or while it stands by
        self._learnt: Tables | None = None
        self._tap: Tap | None = None  #: a new publisher's first events, until forwarded
        self._id_lock: IO[bytes] | None = None
        self.can: Node | None = None
        self.ip: Node | None = None  #: the IP side's node (TCP/IP or Zenoh)
        self._to_ip_sinks: dict[int, _Forward] = {}  # uid -> forwarder on the CAN side
        self._to_can_sinks: dict[int, _Forward] = {}  # uid -> forwarder on the IP side
        self._unwanted_since: dict[int, float] = {}  # uid -> when its IP subscribers went
        self._tasks: list[asyncio.Task[None]] = []
        self.counters = dict.fromkeys(
            (
                f"to_{self.side}",
                "to_can",
                "can_dropped",
                "too_large_for_can",
                "reconcile_errors",
                "pacer_errors",
                "denied",
            ),
            0,
        )
        self._backlog = Backlog(self._reconcile, self.counters)  #: channels to bring in line

    # --- life cycle ------------------------------------------------------------------------

    async def __aenter__(self) -> Gateway:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def start(self) -> None:
        try:
            await self._start()
        except BaseException:
            await self.close()
            raise

    async def _start(self) -> None:
        if isinstance(self._can_spec, CanLink):
            self._link = self._can_spec
        else:
            self._link = CanLink.shared(self._can_spec)
            self._owns_link = True
        if self._host_can_ecb:
            db = self._db
            if db is None:
                if not isinstance(self._can_spec, str):
                    raise ConfigError("a gateway on a CanLink needs db=: the bus has no name")
                db = default_db(self._can_spec)
            self._ecb = CanEcb(self._link, db, bitrate=self.bitrate, recovery=self._recovery)
            self._ecb.on_standby = self._stood_by
            self._ecb.on_serving = self._serving
        self._learnt = Tables(self._link)
        self._learnt.start()
        self._tap = Tap(
            self._link, forwarding=self._to_ip_sinks.__contains__, receives=self._receives,
            own=self._own_txnode, counters=self.counters,
        )  # fmt: skip
        self._tap.start()
        self._tap.wide(self._ecb is None)  # a hosted CAN-ECB's bind gate does its work
        if self._ecb is not None:
            await self._ecb.start()
        else:
            self._link.start()
        if self._node_id is None:
            self._node_id, self._id_lock = claim_node_id(self.name)
        self.can = Node(
            can=self._link, node_id=self._node_id, name=self.name, join_timeout=self._join_timeout
        )
        await self.can.start()
        if self._ecb is None or self._ecb.standby:  # what was bound before we came
            self._learnt.ask_roster(self._can_face_txnode())
        kind, where = self._ip_network
        self.ip = Node(
            broker=where if kind == "broker" else None,
            zenoh=where if kind == "zenoh" else None,
            node_id=self._node_id,
            name=self.name,
            listen=self._listen,
            join_timeout=self._join_timeout,
            tls=self._tls,
            zenoh_config=self._zenoh_config,
        )
        await self.ip.start()
        ip_face = self._ip_face()
        ip_face.on_targets = self._backlog.changed
        ip_face.extra_status = self.status
        self._learnt.on_change = self._backlog.changed
        if self._ecb is not None:
            self._ecb.on_change = self._backlog.changed
            self._ecb.bind_gate = self._until_settled
        self._all_dirty()
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._backlog.work()) for _ in range(RECONCILERS)]
        self._pacer = Pacer(self.can.face, bitrate=self.bitrate, fd=self._link.fd,
                            limit=self._can_queue, counters=self.counters)  # fmt: skip
        self._tasks.append(loop.create_task(self._pacer.run()))
        address = getattr(ip_face, "address", None)  # where TCP publishers reach us
        log.info(
            "gateway %016x between %s (TxNode %s) and %s%s",
            self._node_id,
            self._link.channel_info,
            self.can.stats().get("txnode"),
            ip_face.where,
            ", listening on {}:{}".format(*address) if address else "",
        )

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            for _ in range(CLOSE_TRIES):  # Python 3.11's wait_for can swallow a cancel that
                await asyncio.wait({task}, timeout=1.0)  # meets its result: ask again
                if task.done():
                    break
                task.cancel()
            if task.done():
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            else:
                log.warning("a gateway task did not end when cancelled: %s", task)
        self._tasks.clear()
        for tables in (self._learnt, self._ecb):
            if tables is not None:
                tables.on_change = None
        for node in (self.ip, self.can):
            if node is not None:
                await node.close()
        if self._learnt is not None:
            self._learnt.close()
        if self._tap is not None:
            self._tap.close()
        if self._ecb is not None:
            self._ecb.close()
        if self._link is not None and self._owns_link:
            self._link.release()
        if self._id_lock is not None:
            self._id_lock.close()
            self._id_lock = None

    # --- statistics ------------------------------------------------------------------------

    @property
    def link(self) -> CanLink | None:
        """The CAN bus, shared by the gateway's CAN node and the CAN-ECB it hosts."""
        return self._link

    @property
    def can_ecb(self) -> CanEcb | None:
        """The CAN-ECB the gateway hosts (None with ``host_can_ecb=False``)."""
        return self._ecb

    def stats(self) -> dict[str, int]:
        """Events forwarded each way, drops, and the channels forwarded."""
        can_stats = self.can.stats() if self.can else {}
        ip_stats = self.ip.stats() if self.ip else {}
        return {
            **self.counters,
            "can_queued": len(self._pacer) if self._pacer is not None else 0,
            f"{self.side}_dropped": ip_stats.get("peer_dropped", 0),
            f"{self.side}_lost": ip_stats.get("lost", 0),
            "can_tx_failed": can_stats.get("tx_failed", 0),
            "bindings": can_stats.get("bindings", 0),
            f"forwarding_to_{self.side}": len(self._to_ip_sinks),
            "forwarding_to_can": len(self._to_can_sinks),
            "txnode": can_stats.get("txnode", -1),
        }

    def status(self) -> dict[str, Any]:
        """What ``ups status`` shows for the gateway, next to its TCP node's own tables."""
        return {
            "gateway": {
                **self.stats(),
                "can_bus": self._link.channel_info if self._link else None,
                "txnode": self.can.stats().get("txnode") if self.can else None,
                f"channels_to_{self.side}": [f"0x{uid:016x}" for uid in sorted(self._to_ip_sinks)],
                "channels_to_can": [f"0x{uid:016x}" for uid in sorted(self._to_can_sinks)],
                "can_node": self.can.stats() if self.can else {},
                "can_ecb": self._ecb.stats() if self._ecb else "external",
                "roster": self._learnt.counters if self._learnt else {},
            }
        }

    # --- deciding what to forward ----------------------------------------------------------

    def _tables(self) -> CanEcb | Tables:
        """The tables that say who uses what now: the hosted CAN-ECB's while it serves with
        whole tables, else what the gateway learnt (requests heard, the serving CAN-ECB's
        roster): while the CAN-ECB stands by, or relearns the bus in a recovery window."""
        if self._ecb is not None and not self._ecb.standby and not self._ecb.recovering:
            return self._ecb
        assert self._learnt is not None
        return self._learnt

    def _all_dirty(self) -> None:
        """Every channel either table knows is brought in line (the tables changed roles)."""
        self._backlog.changed_all(
            uid
            for tables in (self._ecb, self._learnt)
            if tables is not None
            for uids in (tables.subscribers, tables.publishers)
            for uid in uids
        )

    def _stood_by(self, reason: str) -> None:
        """The hosted CAN-ECB stands by for another: forward by what that one says."""
        if self._tap is not None:
            self._tap.wide(True)  # a new publisher's binding is no longer ours to hold
        txnode = self._own_txnode()
        if txnode is not None:  # joined: else it asks once it is
            assert self._learnt is not None
            self._learnt.ask_roster(txnode)
        self._all_dirty()

    def _serving(self) -> None:
        """The hosted CAN-ECB serves with whole tables (a recovery ended): they lead again."""
        if self._tap is not None:
            self._tap.wide(False)
        self._all_dirty()

    async def _until_settled(self, uid: int, txnode: int) -> None:
        """Wait until the forwarding of ``uid`` follows the tables (the CAN-ECB's bind gate: a
        new publisher's first events are then forwarded to subscribers already on TCP). Not
        for the gateway's own binding: its reconcile waits for that one (it used to wait out
        the gate's timeout, a second per channel forwarded to CAN)."""
        if self._backlog.busy(uid) and txnode != self._can_face_txnode():
            await self._backlog.settled(uid)

    async def _reconcile(self, uid: int) -> None:
        assert self.can is not None and self.ip is not None
        me = self._can_face_txnode()
        tables = self._tables()
        can_subs = tables.subscribers.get(uid, set()) - {me}
        can_pubs = tables.publishers.get(uid, set()) - {me}
        channel = self._catalog.channel(uid)

        if can_subs and uid not in self._to_can_sinks:  # IP -> CAN
            can_state = await self.can._publishing_state(channel)
            sink = _Forward(self._to_can, can_state)
            try:
                await self.ip._attach(channel, sink)
            except AccessDenied as exc:  # nothing the gateway may not receive reaches the bus
                self._denied(uid, exc)
            else:
                self._to_can_sinks[uid] = sink  # listed once it works
                log.info("forwarding %016x from %s to CAN", uid, self.side)
        elif not can_subs and uid in self._to_can_sinks:
            await self.ip._detach(channel, self._to_can_sinks.pop(uid))
            log.info("stopped forwarding %016x from %s to CAN", uid, self.side)

        ip_state = None
        if can_pubs or can_subs:  # advertise it on the IP side, to learn who subscribes:
            # a channel used on the bus is forwarded from the moment it has IP subscribers,
            # so that a publisher that comes later loses none of its first events
            try:
                ip_state = await self.ip._publishing_state(channel)
            except AccessDenied as exc:
                self._denied(uid, exc)
        wanted = ip_state is not None and self._ip_face().subscribed_elsewhere(uid)
        if wanted:
            self._unwanted_since.pop(uid, None)
        elif uid in self._to_ip_sinks and self._lingers(uid):
            return  # forwarded a while longer: the subscribers may be back soon
        if wanted and uid not in self._to_ip_sinks:  # CAN -> IP
            assert ip_state is not None and self._tap is not None
            sink_ip = _Forward(self._to_ip, ip_state)
            self._tap.forward(uid, lambda data, prio: self._to_ip_data(ip_state, data, prio))
            try:
                await self.can._attach(channel, sink_ip)
            finally:
                self._tap.drop(uid)  # the CAN face receives it now (or could not: tried again)
            self._to_ip_sinks[uid] = sink_ip  # listed once it works
            log.info("forwarding %016x from CAN to %s", uid, self.side)
        elif not wanted and uid in self._to_ip_sinks:
            await self.can._detach(channel, self._to_ip_sinks.pop(uid))
            log.info("stopped forwarding %016x from CAN to %s", uid, self.side)
        elif not wanted and self._tap is not None:
            self._tap.drop(uid)  # nobody on the IP side wants what it kept

    def _lingers(self, uid: int) -> bool:
        """Whether ``uid``, no longer subscribed on the IP side, is still forwarded: for the
        face's ``linger`` seconds (Zenoh: 5 s, a router restarting) its events keep their
        numbers, so that subscribers back in time count what they missed."""
        linger = float(getattr(self._ip_face(), "linger", 0.0))
        loop = asyncio.get_running_loop()
        since = self._unwanted_since.setdefault(uid, loop.time())
        left = since + linger - loop.time()
        if left <= 0:
            del self._unwanted_since[uid]
            return False
        loop.call_later(left, self._backlog.changed, uid)  # look again then
        return True

    def _denied(self, uid: int, exc: AccessDenied) -> None:
        """The TCP-ECB's ACL does not let the gateway's identity carry ``uid`` this way."""
        self.counters["denied"] += 1
        log.warning("not forwarding %016x: %s", uid, exc)

    # --- forwarding ------------------------------------------------------------------------

    def _to_ip(self, ip_state: ChannelState, msg: Message) -> None:
        self._to_ip_data(ip_state, msg.data, msg.priority)

    def _to_ip_data(self, ip_state: ChannelState, data: bytes, priority: int) -> None:
        """An event from CAN (the CAN face's, or what the tap kept) to the IP side."""
        self.counters[self._to_ip_counter] += 1
        self._ip_face().send(ip_state, data, priority)

    def _to_can(self, can_state: ChannelState, msg: Message) -> None:
        assert self._pacer is not None
        self._pacer.put(can_state, msg.data, msg.priority)

    # --- helpers ---------------------------------------------------------------------------

    def _ip_face(self) -> Any:
        """The IP side's face: a ``TcpFace`` or a ``ZenohFace`` (both tell who subscribes
        elsewhere, ``subscribed_elsewhere``, and call ``on_targets`` when that changes)."""
        assert self.ip is not None
        return self.ip.face

    def _receives(self, etag: int) -> bool:
        """Whether the gateway's CAN face receives ``etag`` itself."""
        face: Any = self.can.face if self.can is not None else None  # a CanFace
        return face is not None and bool(face.receives(etag))

    def _own_txnode(self) -> int | None:
        """The CAN face's TxNode (None before it joined): read per tapped frame, so not from
        ``stats()``, which builds a dict."""
        txnode = getattr(self.can.face, "txnode", None) if self.can is not None else None
        return txnode if isinstance(txnode, int) else None

    def _can_face_txnode(self) -> int:
        assert self.can is not None
        return int(self.can.stats()["txnode"])
