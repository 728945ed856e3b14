"""``ups ros2``: a UPS node that is also an rmw_zenoh participant.

The bridge opens a Zenoh session to the ROS 2 system's router and appears in its graph as one
node (liveliness token ``NN``) with a publisher (``MP``) per topic sent to ROS and a
subscription (``MS``) per topic received from it, each with the key expression, type hash,
QoS and GID rmw_zenoh's own would have (``_rmw``).

Forwarding follows the Zenoh face's rule, per topic:

- UPS -> ROS while a Zenoh subscriber matches the topic's key (Zenoh's matching status of the
  bridge's publisher): a ROS subscriber of that exact key, or any whose key expression includes
  it (``0/**``, ``**``: a recorder, a bridge, ``z_sub``), as rmw_zenoh's own publishers would
  feed it; one of another type, type hash or domain has another key and does not count. Only
  then does the bridge subscribe to the channel on the UPS side; when the last subscriber
  leaves it unsubscribes, and nothing more goes to Zenoh.
- ROS -> UPS only while someone on the UPS side subscribes to the channel: the bridge declares
  its ROS subscription (Zenoh subscriber and ``MS`` token) then, and withdraws it when they
  leave. TCP/IP and Zenoh faces say who subscribes elsewhere; a CAN bus is a broadcast medium
  whose subscribers only its CAN-ECB knows, so on CAN the subscription stays declared.
- No reflection: what came from ROS is not sent back to ROS (a ``both`` topic's UPS
  subscription does not take the bridge's own publication, its Zenoh subscriber does not take
  the bridge's own samples), and what came from UPS is not published on UPS.

Every sample put carries rmw_zenoh's attachment (sequence number from 1 per publisher, source
time, the publisher's GID). What comes from ROS passes ``_admit`` first: at most the topic's
``max_rate`` samples a second after a ``burst`` (``rate_limited``), each publisher's sequence
numbers followed, a gap counted as loss (``ros_lost``) only within what that rate could have
carried, a jump beyond it a restart or a forgery (``ros_jumps``). A sample without rmw_zenoh's
attachment (a plain Zenoh program putting CDR on the key) is forwarded all the same and counted
(``no_attachment``). A value that does not fit the other side is dropped and counted
(``out_of_range``), as is a payload that does not decode (``malformed``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ups import BrokerUnavailable, Channel, ConfigError, DecodeError, UpsError
from ups._message import Message
from ups._zenohface import STATUS_PREFIX, zenoh_config

from ._admit import Admission, Gate
from ._mapping import Bridge
from ._rmw import (
    PUBLISHER,
    RMW_ZENOH_COMMIT,
    SUBSCRIPTION,
    attachment,
    entity_token,
    gid,
    node_token,
)
from ._topic import TopicMap, Unrepresentable

if TYPE_CHECKING:
    from ups import Node, Subscription

log = logging.getLogger("ups.ros2")

RX_PENDING = 65536  #: ROS samples handed to the event loop, not yet handled (then: rx_overflow)
COUNTERS = ("to_ros", "from_ros", "out_of_range", "malformed", "no_attachment", "ros_lost",
            "ros_jumps", "rate_limited", "unmatched", "reflected", "rx_overflow",
            "reconcile_errors")  # fmt: skip


@dataclass(slots=True)
class _Live:
    """A topic at run time: its Zenoh entities, what is forwarded now, its counters."""

    map: TopicMap
    entity: int
    publisher: Any = None
    token: Any = None  #: MP, declared for as long as the bridge runs
    listener: Any = None  #: the publisher's matching listener (kept: dropping it ends it)
    gid: bytes = b""
    matching: bool = False  #: a ROS subscriber matches the key (UPS -> ROS)
    subscription: Subscription | None = None  #: on the UPS side, while matching
    sequence: int = 0
    ros_sub: Any = None  #: the Zenoh subscriber (ROS -> UPS), while wanted
    ros_token: Any = None  #: its MS token
    gate: Gate | None = None  #: its rate bound and loss credit (ROS -> UPS)
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        ("sent", "received", "out_of_range", "malformed", "rate_limited"), 0))  # fmt: skip

    @property
    def publisher_id(self) -> int:
        """Its publisher's entity id in the node (topic n: 2n - 1)."""
        return 2 * self.entity - 1

    @property
    def subscription_id(self) -> int:
        """Its subscription's entity id in the node (topic n: 2n)."""
        return 2 * self.entity


class RosBridge:
    """The map's topics between ``node`` (any UPS network) and the ROS 2 system whose Zenoh
    router is at ``ros`` (or as the Zenoh config file ``ros_config`` says)."""

    def __init__(
        self,
        node: Node,
        bridge: Bridge,
        ros: str,
        ros_config: str | Path | None = None,
        join_timeout: float = 30.0,
    ) -> None:
        """Checks ``ros`` at once (before the node joins); ``start`` waits up to
        ``join_timeout`` seconds for the router to answer."""
        if ros and "/" not in ros:  # HOST:PORT: say the form, not Zenoh's internals
            raise ConfigError(f"bad ROS 2 router endpoint {ros!r}: it names no protocol (did you "
                              f"mean --ros tcp/{ros}?)")  # fmt: skip
        self.node = node
        self.bridge = bridge
        self.ros = ros
        self.join_timeout = join_timeout
        self._config = zenoh_config(ros, ros_config)  # says so when Zenoh is not installed
        self.counters = dict.fromkeys(COUNTERS, 0)
        now = time.monotonic()
        self.topics = [
            _Live(t, i + 1, gate=Gate.new(t.max_rate, t.burst, now) if t.from_ros else None)
            for i, t in enumerate(bridge.topics)
        ]
        self._session: Any = None
        self._tokens: list[Any] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._dirty: set[int] = set()
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._pending = 0
        self._pending_lock = threading.Lock()  # admission and _pending, from Zenoh's threads
        self._admission = Admission(self.counters)
        self._publishing: int | None = None  # the UID being published from ROS, this instant
        self._status_queryable: Any = None
        self._tasks: set[asyncio.Task[None]] = set()
        self.zid = ""

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        import zenoh

        self._loop = asyncio.get_running_loop()
        self._session = await self._open()
        self.zid = str(self._session.zid())
        b = self.bridge
        self._tokens.append(self._session.liveliness().declare_token(
            node_token(b.domain, self.zid, 0, b.namespace, b.node)))  # fmt: skip
        for live in self.topics:
            t = live.map
            if t.to_ros:
                token = entity_token(b.domain, self.zid, 0, live.publisher_id, PUBLISHER,
                                     b.namespace, b.node, t.topic, t.type, t.type_hash,
                                     t.qos)  # fmt: skip
                live.gid = gid(token)
                live.publisher = self._session.declare_publisher(
                    t.key,
                    congestion_control=zenoh.CongestionControl.DROP,
                    reliability=zenoh.Reliability.RELIABLE
                    if t.qos.reliability == 1
                    else zenoh.Reliability.BEST_EFFORT,
                    allowed_destination=zenoh.Locality.REMOTE,  # never our own subscriber
                )
                live.listener = live.publisher.declare_matching_listener(
                    lambda status, i=live.entity: self._threadsafe(self._matched, i,
                                                                  status.matching))  # fmt: skip
                live.token = self._session.liveliness().declare_token(token)
            if t.from_ros:
                size = t.channel.size
                await self.node.advertise(t.channel.channel, max_size=size or 0)
        face: Any = self.node.face
        if hasattr(face, "subscribed_elsewhere"):  # TCP/IP and Zenoh say who subscribes
            face.on_targets = self._targets
        if hasattr(face, "extra_status"):
            face.extra_status = self.status
        if not type(face).__name__.startswith("Zenoh"):  # answer `ups status --zenoh` here
            self._status_queryable = self._session.declare_queryable(
                f"{STATUS_PREFIX}/{self.node.node_id:016x}", self._on_status_query
            )
        for live in self.topics:  # in the graph, as it should be now, before saying so
            self._dirty.discard(live.entity)
            await self._reconcile(live)
        self._task = asyncio.get_running_loop().create_task(self._reconcile_loop())
        self._wake.set()  # what changed meanwhile
        log.info("ROS 2 node %s%s on %s (Zenoh id %s, domain %d): %d topics",
                 b.namespace.rstrip("/") + "/", b.node, self.ros, self.zid, b.domain,
                 len(self.topics))  # fmt: skip

    async def _open(self) -> Any:
        """The Zenoh session to the ROS 2 router, which may start after the bridge: tried again
        (0.1 s, doubling to 1 s) for up to ``join_timeout`` seconds, as the UPS side waits for
        its CAN-ECB or TCP-ECB; then ``BrokerUnavailable`` saying what to start."""
        import zenoh

        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.join_timeout
        delay, said = 0.1, False
        while True:
            try:  # opening connects, or fails at once when nothing listens: not on the loop
                return await asyncio.to_thread(zenoh.open, self._config)
            except zenoh.ZError as exc:
                if loop.time() + delay > deadline:
                    raise BrokerUnavailable(self._unavailable(exc)) from None
            if not said:
                log.warning("waiting for the ROS 2 router at %s (up to %g s)", self.ros,
                            self.join_timeout)  # fmt: skip
                said = True
            await asyncio.sleep(delay)
            delay = min(delay * 2, 1.0)

    def _unavailable(self, exc: BaseException) -> str:
        """Why the router could not be joined, for people: Zenoh's text without its Rust
        source location, and what to start there."""
        reason = re.sub(r"\s+at \S+\.rs:\d+.*", "", str(exc), flags=re.S).strip()
        if reason.startswith("Unable to connect"):
            reason = "nothing answers there"
        return (f"could not join the ROS 2 router at {self.ros} within {self.join_timeout:g} s "
                f"({reason}); start rmw_zenohd there (ros2 run rmw_zenoh_cpp rmw_zenohd), or "
                f"where ROS 2 is absent 'ups zenoh-router --listen {self.ros}'")  # fmt: skip

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        for task in list(self._tasks):
            task.cancel()
        session, self._session = self._session, None
        for live in self.topics:
            if live.subscription is not None:
                with contextlib.suppress(Exception):
                    await self.node.unsubscribe(live.subscription)
                live.subscription = None
        if session is not None:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(session.close)

    # --- deciding what is forwarded ---------------------------------------------------------

    def _threadsafe(self, callback: Any, *args: Any) -> None:
        loop = self._loop
        if loop is not None and self._session is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(callback, *args)

    def _matched(self, entity: int, matching: bool) -> None:
        live = self.topics[entity - 1]
        live.matching = matching
        self._changed(entity)

    def _targets(self, uid: int) -> None:
        for live in self.topics:
            if live.map.channel.uid == uid:
                self._changed(live.entity)

    def _changed(self, entity: int) -> None:
        self._dirty.add(entity)
        self._wake.set()

    async def _reconcile_loop(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._dirty:
                live = self.topics[self._dirty.pop() - 1]
                try:
                    await self._reconcile(live)
                except Exception:  # tried again at the next change
                    self.counters["reconcile_errors"] += 1
                    log.exception("could not bring %s in line", live.map.topic)

    async def _reconcile(self, live: _Live) -> None:
        t = live.map
        if t.to_ros:
            if live.publisher is not None:  # what Zenoh says now (the listener may lag)
                live.matching = bool(live.publisher.matching_status.matching)
            if live.matching and live.subscription is None:

                def forward(msg: Message, live: _Live = live) -> None:
                    self._to_ros(live, msg)

                live.subscription = await self.node.subscribe(t.channel.channel, callback=forward)
                log.info("forwarding %s to ROS as %s", t.channel.channel, t.topic)
            elif not live.matching and live.subscription is not None:
                subscription, live.subscription = live.subscription, None
                await self.node.unsubscribe(subscription)
                log.info("stopped forwarding %s to ROS: no subscriber", t.channel.channel)
        if t.from_ros:
            elsewhere = getattr(self.node.face, "subscribed_elsewhere", None)
            wanted = True if elsewhere is None else bool(elsewhere(t.channel.uid))
            session = self._session
            if wanted and live.ros_sub is None and session is not None:
                import zenoh

                b = self.bridge

                def received(sample: Any, live: _Live = live) -> None:
                    self._received(live, sample)

                live.ros_sub = session.declare_subscriber(
                    t.key, received,
                    allowed_origin=zenoh.Locality.REMOTE,  # never our own samples
                )  # fmt: skip
                live.ros_token = session.liveliness().declare_token(entity_token(
                    b.domain, self.zid, 0, live.subscription_id, SUBSCRIPTION, b.namespace, b.node,
                    t.topic, t.type, t.type_hash, t.qos))  # fmt: skip
                log.info("forwarding %s from ROS to %s", t.topic, t.channel.channel)
            elif not wanted and live.ros_sub is not None:
                for entity in (live.ros_token, live.ros_sub):
                    with contextlib.suppress(Exception):
                        entity.undeclare()
                live.ros_sub = live.ros_token = None
                log.info("stopped forwarding %s from ROS: no UPS subscriber", t.topic)

    # --- UPS -> ROS --------------------------------------------------------------------------

    def _to_ros(self, live: _Live, msg: Message) -> None:
        if self._publishing == msg.channel.uid:  # our own publication, from ROS
            self.counters["reflected"] += 1
            return
        if not live.matching or live.publisher is None:  # the last subscriber just left
            self.counters["unmatched"] += 1
            return
        try:
            payload = live.map.ros_payload(msg.data, msg.timestamp)
        except Unrepresentable as exc:
            self._count(live, "out_of_range", exc)
            return
        except DecodeError as exc:
            self._count(live, "malformed", exc)
            return
        live.sequence += 1
        live.publisher.put(payload, attachment=attachment(live.sequence, time.time_ns(),
                                                          live.gid))  # fmt: skip
        live.counts["sent"] += 1
        self.counters["to_ros"] += 1

    # --- ROS -> UPS --------------------------------------------------------------------------

    def _received(self, live: _Live, sample: Any) -> None:  # in a Zenoh thread
        raw = sample.attachment
        extra = None if raw is None else raw.to_bytes()
        gate = live.gate
        assert gate is not None  # a from_ros topic
        with self._pending_lock:
            if not self._admission.admit(gate, extra, time.monotonic()):
                live.counts["rate_limited"] += 1
                return
            if self._pending >= RX_PENDING:
                self.counters["rx_overflow"] += 1
                return
            self._pending += 1
        self._threadsafe(self._from_ros, live, sample.payload.to_bytes())

    def _from_ros(self, live: _Live, payload: bytes) -> None:
        with self._pending_lock:
            self._pending -= 1
        if live.ros_sub is None:  # withdrawn meanwhile
            return
        try:
            data = live.map.ups_payload(payload)
        except Unrepresentable as exc:
            self._count(live, "out_of_range", exc)
            return
        except DecodeError as exc:
            self._count(live, "malformed", exc)
            return
        live.counts["received"] += 1
        self.counters["from_ros"] += 1
        channel = live.map.channel.channel
        self._publishing = channel.uid
        try:
            self.node.publish_nowait(channel, data)
        except ConfigError:  # larger than the channel's binding: bind it larger first
            task = asyncio.get_running_loop().create_task(self._publish(channel, data))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        finally:
            self._publishing = None

    async def _publish(self, channel: Channel, data: bytes) -> None:
        """Bind ``channel`` for events of ``data``'s size, then publish it (on CAN, a larger
        size class; see ``Node.advertise``)."""
        try:
            await self.node.advertise(channel, max_size=len(data))
            self._publishing = channel.uid
            self.node.publish_nowait(channel, data)
        except UpsError as exc:  # more than the network carries, the node closing ...
            self.counters["malformed"] += 1
            log.warning("could not publish a message of %s on UPS: %s", channel, exc)
        finally:
            self._publishing = None

    def _count(self, live: _Live, what: str, exc: Exception) -> None:
        live.counts[what] += 1
        self.counters[what] += 1
        if self.counters[what] & (self.counters[what] - 1) == 0:  # the 1st, 2nd, 4th, 8th ...
            log.warning("%s: dropped (%s, %d so far): %s", live.map.topic, what.replace("_", " "),
                        self.counters[what], exc)  # fmt: skip

    # --- status ------------------------------------------------------------------------------

    def stats(self) -> dict[str, int]:
        return {
            **self.counters,
            "topics": len(self.topics),
            "to_ros_forwarding": sum(live.subscription is not None for live in self.topics),
            "from_ros_forwarding": sum(live.ros_sub is not None for live in self.topics),
        }

    def status(self) -> dict[str, Any]:
        """The bridge, its topics and counters (``ups status`` shows it as ``ros2``)."""
        b = self.bridge
        return {
            "ros2": {
                "router": self.ros,
                "zenoh_id": self.zid,
                "node": f"{b.namespace.rstrip('/')}/{b.node}",
                "domain": b.domain,
                "distro": b.distro,
                "map": b.path,
                "rmw_zenoh_commit": RMW_ZENOH_COMMIT,
                "topics": [
                    {
                        **live.map.describe(),
                        "to_ros_forwarding": live.subscription is not None,
                        "from_ros_forwarding": live.ros_sub is not None,
                        "sequence": live.sequence,
                        **live.counts,
                    }
                    for live in self.topics
                ],
                "stats": self.stats(),
            }
        }

    def _on_status_query(self, query: Any) -> None:  # in a Zenoh thread
        self._threadsafe(self._answer_status, query)

    def _answer_status(self, query: Any) -> None:
        node = self.node
        answer = {
            "node_id": f"0x{node.node_id:016x}",
            "name": node.name,
            "zenoh_id": self.zid,
            "stats": node.stats(),
            "subscribed": [f"0x{t.map.channel.uid:016x}" for t in self.topics if t.subscription],
            "published": [f"0x{t.map.channel.uid:016x}" for t in self.topics if t.map.from_ros],
            **self.status(),
        }
        try:
            query.reply(query.key_expr, json.dumps(answer))
        except Exception:  # a querier that left
            log.debug("could not answer a status query", exc_info=True)
        finally:
            with contextlib.suppress(Exception):
                query.drop()
