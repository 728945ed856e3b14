"""The Zenoh face of a node: UPS channels as Zenoh key expressions, routed by Zenoh.

A node opens a Zenoh session (a client of the router at ``zenoh=``, or whatever its Zenoh
config file says) and maps each channel onto one key expression: ``ups/<uid>`` and, when the
channel was named, ``ups/<uid>/<name>``. A subscription covers ``ups/<uid>/**``, so it hears
publishers that know the name and those that know only the UID (a gateway forwarding from
CAN). The payload is the event's data as it is, so plain Zenoh programs read and write UPS
channels; the attachment carries what UPS adds: the UPS priority, the publishing node and a
sequence number per channel, from which subscribers count what never arrived. See
docs/protocol.md, "UPS on Zenoh".

Zenoh calls back from its own threads: received samples wait in a queue of ``RX_QUEUE``
(counted when full, ``rx_overflow``) until the event loop hands them to the node.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import re
import struct
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ._errors import BrokerUnavailable, ConfigError, PayloadTooLarge
from ._extras import require
from ._zenohwatch import ZenohWatches

if TYPE_CHECKING:
    from ._face import ChannelState, FaceContext, Found

log = logging.getLogger("ups.zenoh")

PREFIX = "ups"  #: the first chunk of every UPS key expression
STATUS_PREFIX = f"{PREFIX}/@node"  #: ``<prefix>/<node id>`` answers a get with the status
SYNC_KEY = f"{PREFIX}/@sync"  #: queried (nobody answers) for a round trip through the router
SYNC_TIMEOUT = 2.0  #: seconds a bind waits for that round trip (then: sync_timeouts)
MAX_DATA = 1 << 20  #: the largest event (as on TCP/IP)
RX_QUEUE = 65536  #: samples received, not yet handed to the node (then: rx_overflow)
MAX_SOURCES = 4096  #: (publisher, channel) pairs whose numbers are followed (then: forgotten)
#: the attachment of a UPS event: version 1, UPS priority, publishing node id, sequence number
ATTACHMENT = struct.Struct(">BBQQ")
VERSION = 1
_DRAIN_BATCH = 512  # samples handed over per event-loop pass
_RETRY_FIRST = 0.05
_RETRY_MAX = 1.0

#: the node options a Zenoh face takes (see ``Node``)
OPTIONS = frozenset({"config"})


def build(where: str, context: FaceContext, *, config: str | Path | None = None) -> ZenohFace:
    return ZenohFace(where, context, config=config)


def channel_key(uid: int, name: str | None) -> str:
    """The key expression a channel's events are put on."""
    key = f"{PREFIX}/{uid:016x}"
    return f"{key}/{name}" if name is not None and _plain_key(name) else key


def subscription_key(uid: int) -> str:
    """The key expression a subscription to a channel covers."""
    return f"{PREFIX}/{uid:016x}/**"


def _plain_key(name: str) -> bool:
    """Whether ``name`` can be chunks of a key expression as it is (no wildcard or verbatim
    chunk, no empty chunk); other names leave the key at the UID."""
    return all(
        chunk and chunk[0] != "@" and not any(c in chunk for c in "*$?#")
        for chunk in name.split("/")
    )


def to_zenoh_priority(priority: int) -> int:
    """UPS priority 0..255 (0 highest) onto Zenoh's 1 (RealTime) .. 7 (Background)."""
    return 1 + priority * 7 // 256


def from_zenoh_priority(band: int) -> int:
    """The lowest UPS priority that maps onto Zenoh priority ``band`` (for events that come
    without a UPS attachment)."""
    return -(-(band - 1) * 256 // 7)


def require_zenoh() -> None:
    """Raise ``ConfigError`` saying how to install Zenoh when it is not installed."""
    require("zenoh", "zenoh", "Zenoh is not installed (eclipse-zenoh)")


def zenoh_config(endpoint: str, config: str | Path | None, mode: str = "client") -> Any:
    """A Zenoh config: the file's when given, else Zenoh's defaults, with ``endpoint`` added
    to connect to. ``mode`` and multicast scouting off, unless the file names them (a key
    ``mode``, a key ``multicast``): UPS never scouts a real LAN unasked."""
    require_zenoh()
    import zenoh

    text = ""
    try:
        if config is not None:
            text = Path(config).read_text()
            conf = zenoh.Config.from_file(str(config))
        else:
            conf = zenoh.Config()
    except (zenoh.ZError, OSError, ValueError) as exc:
        raise ConfigError(f"bad Zenoh config {config}: {exc}") from None
    if not re.search(r"""\bmode["']?\s*:""", text):
        conf.insert_json5("mode", json.dumps(mode))
    if not re.search(r"""\bmulticast["']?\s*:""", text):
        conf.insert_json5("scouting/multicast/enabled", "false")
    if endpoint:
        if "/" not in endpoint:  # HOST:PORT, as for --broker: say the form, not Zenoh's internals
            raise ConfigError(f"bad Zenoh endpoint {endpoint!r}: it names no protocol (did you "
                              f"mean --zenoh tcp/{endpoint}?)")  # fmt: skip
        try:
            conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        except zenoh.ZError as exc:
            why = re.sub(r"\s+at /\S+\.rs:\d+.*", "", str(exc), flags=re.S)  # no Rust paths
            raise ConfigError(f"bad Zenoh endpoint {endpoint!r}: {why}") from None
    return conf


class ZenohFace:
    """A node's face on a Zenoh network."""

    max_payload = MAX_DATA
    #: seconds a gateway keeps forwarding a channel whose last subscriber stopped matching (a
    #: router restarting): events keep their numbers, and subscribers count what they missed
    linger = 5.0

    def __init__(
        self, endpoint: str, context: FaceContext, *, config: str | Path | None = None
    ) -> None:
        if not endpoint and config is None:
            raise ConfigError("a Zenoh node needs an endpoint (zenoh='tcp/HOST:PORT') or a config")
        self.where = f"the Zenoh router at {endpoint}" if endpoint else f"Zenoh as {config} says"
        self._endpoint = endpoint
        self._config = zenoh_config(endpoint, config)  # a bad file fails before anything opens
        self.node_id = context.node_id
        self.name = context.name
        self._deliver = context.deliver
        self._channels = context.channels
        self._node_stats = context.node_stats
        self._join_timeout = context.join_timeout
        self._session: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._publishers: dict[int, dict[int, Any]] = {}  # uid -> Zenoh priority -> publisher
        self._keys: dict[int, str] = {}  # uid -> the key its events are put on
        self._matching: dict[int, bool] = {}  # uid -> whether a remote subscriber matches
        self._listeners: dict[int, Any] = {}  # uid -> matching listener
        self._subscribers: dict[int, Any] = {}  # uid -> Zenoh subscriber
        self._seq: dict[int, int] = {}  # uid -> this node's next number on it
        self._expected: dict[tuple[int, int], int] = {}  # (publisher, uid) -> next number
        #: samples: UID, data, attachment, Zenoh priority, receive time, and the channel's name
        #: when it came by a pattern (see _zenohwatch), else None
        self._rx: collections.deque[tuple[int, bytes, bytes | None, int, float, str | None]] = (
            collections.deque()
        )
        self._watches = ZenohWatches(self._subscribers, self._expected)
        self._rx_scheduled = False
        self._rx_lock = threading.Lock()  # Zenoh may call back from several threads
        self._queryable: Any = None
        self._closed = False
        self._unreported = 0
        self._reporter: asyncio.TimerHandle | None = None
        #: called with a UID when its first remote subscriber comes or its last one goes
        self.on_targets: Any = None
        #: more for the status (the gateway's)
        self.extra_status: Any = None
        self.counters = dict.fromkeys(
            ("sent", "unmatched", "received", "lost", "foreign", "too_large", "rx_overflow",
             "unsubscribed", "forgotten", "restarts", "sync_timeouts"), 0,
        )  # fmt: skip

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        import zenoh

        self._loop = loop = asyncio.get_running_loop()
        deadline = None if self._join_timeout is None else loop.time() + self._join_timeout
        delay = _RETRY_FIRST
        while True:
            try:  # opening connects (or fails at once when nothing listens): not on the loop
                self._session = await asyncio.to_thread(zenoh.open, self._config)
                break
            except zenoh.ZError as exc:
                if deadline is not None and loop.time() + delay > deadline:
                    raise BrokerUnavailable(self._unavailable(exc)) from None
                await asyncio.sleep(delay)
                delay = min(delay * 2, _RETRY_MAX)
        self._queryable = self._session.declare_queryable(
            f"{STATUS_PREFIX}/{self.node_id:016x}", self._on_status_query
        )
        self._reporter = loop.call_later(1.0, self._report)
        log.info("node %016x joined %s (Zenoh id %s)", self.node_id, self.where,
                 self._session.zid())  # fmt: skip

    def _unavailable(self, exc: BaseException) -> str:
        """Why joining failed, for people (Zenoh's own text without its source location)."""
        waited = f" within {self._join_timeout:g} s" if self._join_timeout else ""
        reason = re.sub(r"\s+at \S+\.rs:\d+\.?\s*$", "", str(exc)).strip()
        if reason.startswith("Unable to connect"):
            reason = "nothing answers there"
        router = f"'ups zenoh-router --listen {self._endpoint}'" if self._endpoint else "one"
        return f"could not join {self.where}{waited} ({reason}); start a router with {router}"

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._reporter is not None:
            self._reporter.cancel()
        self._watches.close()
        session, self._session = self._session, None
        if session is not None:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(session.close)
        self._report()

    def stats(self) -> dict[str, int]:
        return {
            **self.counters,
            "router_connected": int(self._connected()),
            "rx_queued": len(self._rx),
        }

    def status(self) -> dict[str, Any]:
        """What a get on ``ups/@node/<node id>`` is answered with (``ups status --zenoh``)."""
        return {
            "node_id": f"0x{self.node_id:016x}",
            "name": self.name,
            "zenoh_id": str(self._session.zid()) if self._session is not None else None,
            "stats": self._node_stats(),
            "subscribed": [f"0x{uid:016x}" for uid in sorted(self._subscribers)],
            "published": [f"0x{uid:016x}" for uid in sorted(self._keys)],
            "names": {
                f"0x{uid:016x}": state.channel.name
                for uid, state in self._channels.items()
                if state.channel.name is not None and (uid in self._keys or state.subs)
            },
            **(self.extra_status() if self.extra_status is not None else {}),
        }

    # --- the Face protocol -----------------------------------------------------------------

    async def bind(self, state: ChannelState, subscribe: bool, size: int = 0) -> None:
        state.max_size = self.max_payload
        uid = state.channel.uid
        session = self._live_session()
        if subscribe:
            if uid not in self._subscribers:
                self._subscribers[uid] = session.declare_subscriber(
                    subscription_key(uid), lambda sample, uid=uid: self._receive(uid, sample)
                )
                await self._sync()  # the router has it: what is put from now on reaches us
            return
        if uid not in self._keys:
            self._keys[uid] = channel_key(uid, state.channel.name)
            self._seq.setdefault(uid, 0)
            publisher = self._publisher(uid, to_zenoh_priority(state.priority))
            self._matching[uid] = False
            self._listeners[uid] = publisher.declare_matching_listener(
                lambda status, uid=uid: self._threadsafe(self._on_matching, uid, status.matching)
            )
            await self._sync()  # the router told us of the subscribers it knows
            self._matching[uid] = bool(publisher.matching_status.matching)

    async def grow(self, state: ChannelState, size: int) -> None:
        raise PayloadTooLarge(
            f"{size} bytes do not fit one event on {state.channel} (at most {self.max_payload})"
        )

    async def unsubscribe(self, state: ChannelState) -> None:
        uid = state.channel.uid
        subscriber = self._subscribers.pop(uid, None)
        if subscriber is not None and self._session is not None:
            with contextlib.suppress(Exception):
                subscriber.undeclare()
        for key in [key for key in self._expected if key[1] == uid]:
            del self._expected[key]

    def send(self, state: ChannelState, data: bytes, priority: int) -> None:
        uid = state.channel.uid
        band = to_zenoh_priority(priority)
        publisher = self._publishers[uid].get(band) or self._publisher(uid, band)
        seq = self._seq[uid]
        self._seq[uid] = seq + 1
        publisher.put(data, attachment=ATTACHMENT.pack(VERSION, priority, self.node_id, seq))
        self.counters["sent"] += 1
        if not self._matching[uid]:  # no subscriber reached (e.g. its router restarting)
            self.counters["unmatched"] += 1

    async def room(self, state: ChannelState) -> None:
        """Zenoh queues and drops on its own (congestion control "drop"): nothing to wait for
        here; what a subscriber misses it counts from the sequence numbers."""

    async def watch(self, pattern: str, found: Found) -> None:
        """Names travel in keys: a channel is found with its first event that carries its
        name (see _zenohwatch)."""
        self._watches.declare(self._live_session(), pattern, found, self._receive)
        await self._sync()  # the router has it: what is put from now on reaches us

    async def unwatch(self, pattern: str) -> None:
        self._watches.undeclare(pattern)

    async def _sync(self) -> None:
        """One round trip through the router: a get that nobody answers ends when the router
        says so, after everything it sent us before (its answer to our declarations: who
        subscribes to what we just declared to publish)."""
        import zenoh

        loop = asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()

        def finished() -> None:  # in a Zenoh thread
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_resolve, done)

        self._live_session().get(
            SYNC_KEY, zenoh.handlers.Callback(lambda reply: None, finished), timeout=SYNC_TIMEOUT
        )
        try:
            async with asyncio.timeout(SYNC_TIMEOUT + 1.0):
                await done
        except TimeoutError:
            self.counters["sync_timeouts"] += 1

    def subscribed_elsewhere(self, uid: int) -> bool:
        """Whether a subscriber outside this session matches ``uid`` (for published channels)."""
        return self._matching.get(uid, False)

    # --- publishing ------------------------------------------------------------------------

    def _publisher(self, uid: int, band: int) -> Any:
        """``uid``'s publisher at Zenoh priority ``band``: events go only to other sessions
        (the node delivers locally itself), dropped by Zenoh rather than blocking the loop."""
        import zenoh

        P = zenoh.Priority
        priorities = (P.REAL_TIME, P.INTERACTIVE_HIGH, P.INTERACTIVE_LOW, P.DATA_HIGH, P.DATA,
                      P.DATA_LOW, P.BACKGROUND)  # fmt: skip
        publisher = self._live_session().declare_publisher(
            self._keys[uid],
            priority=priorities[band - 1],
            congestion_control=zenoh.CongestionControl.DROP,
            reliability=zenoh.Reliability.RELIABLE,
            allowed_destination=zenoh.Locality.REMOTE,
        )
        self._publishers.setdefault(uid, {})[band] = publisher
        return publisher

    def _on_matching(self, uid: int, matching: bool) -> None:
        if self._matching.get(uid) == matching or uid not in self._keys:
            return
        self._matching[uid] = matching
        if self.on_targets is not None:
            self.on_targets(uid)

    # --- receiving -------------------------------------------------------------------------

    def _receive(self, uid: int, sample: Any, name: str | None = None) -> None:
        """Queue a sample for the event loop (in a Zenoh thread); ``name``: it came by a
        pattern, under that name."""
        rx = self._rx
        if len(rx) >= RX_QUEUE:
            self.counters["rx_overflow"] += 1
            return
        attachment = sample.attachment
        rx.append((
            uid,
            sample.payload.to_bytes(),
            None if attachment is None else attachment.to_bytes(),
            int(sample.priority),
            time.time(),
            name,
        ))  # fmt: skip
        if not self._rx_scheduled:
            with self._rx_lock:
                if not self._rx_scheduled:
                    self._rx_scheduled = True
                    self._threadsafe(self._drain)

    def _threadsafe(self, callback: Any, *args: Any) -> None:
        loop = self._loop
        if loop is not None and not self._closed:
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(callback, *args)

    def _drain(self) -> None:
        """Hand received samples to the node, a batch per event-loop pass."""
        self._rx_scheduled = False
        rx, channels, counters = self._rx, self._channels, self.counters
        for _ in range(_DRAIN_BATCH):
            if not rx:
                return
            uid, data, attachment, band, ts, name = rx.popleft()
            if name is not None and not self._watches.discovered(uid, name):
                counters["foreign"] += 1  # a name that is not its UID's: not a UPS key
                continue
            state = channels.get(uid)
            if state is None or not state.subs or (name is None and uid not in self._subscribers):
                counters["unsubscribed"] += 1
                continue
            if len(data) > MAX_DATA:
                counters["too_large"] += 1
                continue
            if attachment is not None and len(attachment) == ATTACHMENT.size:
                version, priority, source, seq = ATTACHMENT.unpack(attachment)
                if version == VERSION:
                    if self._watches.duplicate(source, uid, seq, name is not None):
                        continue
                    self._follow(source, uid, seq)
                    counters["received"] += 1
                    self._deliver(state, data, priority, source, ts)
                    continue
            counters["foreign"] += 1  # a plain Zenoh publisher's: no UPS numbers to follow
            counters["received"] += 1
            self._deliver(state, data, from_zenoh_priority(band), None, ts)
        with self._rx_lock:  # more than a batch: the rest on the next pass
            if rx and not self._rx_scheduled:
                self._rx_scheduled = True
                asyncio.get_running_loop().call_soon(self._drain)

    def _follow(self, source: int, uid: int, seq: int) -> None:
        """Count the numbers ``source`` skipped on ``uid``: events lost on the way."""
        key = (source, uid)
        expected = self._expected.get(key)
        if expected is None:
            if len(self._expected) >= MAX_SOURCES:
                del self._expected[next(iter(self._expected))]
                self.counters["forgotten"] += 1
        elif seq > expected:
            self.counters["lost"] += seq - expected
            self._unreported += seq - expected
        elif seq < expected:  # the publisher started again: its numbers too
            self.counters["restarts"] += 1
        self._expected[key] = seq + 1

    # --- status ------------------------------------------------------------------------------

    def _on_status_query(self, query: Any) -> None:  # in a Zenoh thread
        self._threadsafe(self._answer_status, query)

    def _answer_status(self, query: Any) -> None:
        try:
            query.reply(query.key_expr, json.dumps(self.status()))
        except Exception:  # a querier that left: nothing to answer
            log.debug("could not answer a status query", exc_info=True)
        finally:
            with contextlib.suppress(Exception):
                query.drop()

    def _report(self) -> None:
        """Log what was lost since the last report, once a second."""
        if self._unreported:
            log.warning("lost %d events on the way (numbers skipped)", self._unreported)
            self._unreported = 0
        if not self._closed and self._loop is not None:
            self._reporter = self._loop.call_later(1.0, self._report)

    def _connected(self) -> bool:
        session = self._session
        if session is None:
            return False
        with contextlib.suppress(Exception):
            return bool(session.info.routers_zid() or session.info.peers_zid())
        return False

    def _live_session(self) -> Any:
        if self._session is None:
            raise BrokerUnavailable("the Zenoh session is closed")
        return self._session


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)
