"""The live view of a network that ``ups monitor`` and ``ups console`` show.

``Live`` is the model: channels (rate, count, last value decoded by the catalog, publishers),
nodes (joining, falling silent, leaving), drops, foreign traffic and, on CAN, the bus load.
It is fed by one of two feeds and read through ``snapshot()``, a JSON-able dict:

- on CAN, ``feed_can`` listens and never sends: bindings come from the CAN-ECB's database (when
  it is on this host) and from the management frames heard (``ups._bindings``);
- on TCP/IP, ``feed_tcp`` joins as a node, asks the TCP-ECB for its Status every second and
  subscribes to every channel it lists (or to those given): the TCP-ECB is not on the data
  path, so only a subscriber sees events.

On TCP/IP and Zenoh, the JAUS components on the network (``ups jaus`` nodes) are shown with
their state, controller and the OCUs connected, from each one's status.

Bounds (each counted when hit, in ``snapshot()["untracked"]``): ``MAX_CHANNELS`` channels,
``MAX_NODES`` nodes and ``MAX_JAUS`` JAUS components are tracked; ``HISTORY`` points per
channel are kept for plots, ``RECENT`` lines of who joined or left.
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .._catalog import Catalog

if TYPE_CHECKING:
    import can

    from .._bindings import Bindings
    from .._node import Node
    from ._net import IpNetwork

WINDOW = 5.0  #: seconds over which rates and the bus load are averaged
SILENT = 5.0  #: a CAN node not heard for this long is shown as silent
HISTORY = 600  #: points (time, values) kept per channel, for the console's plot
RECENT = 20  #: lines of nodes joining and leaving kept
MAX_CHANNELS = 4096  #: channels tracked; the others are counted, not shown
MAX_NODES = 1024  #: nodes tracked; the others are counted, not shown
MAX_JAUS = 8  #: JAUS components (``ups jaus`` nodes) whose OCUs are shown; the others counted
JAUS_NODE = "ups-jaus"  #: the name a ``ups jaus`` node joins with
MAX_PENDING = 65536  #: CAN frames waiting for a busy loop; more are dropped and counted
QUEUE = 1024  #: TCP/IP events queued per channel; more are dropped and counted


@dataclass
class _Channel:
    key: str  #: the UID in hex, or "etag 0x0012" while its channel is unknown
    uid: int | None
    name: str | None
    etag: int | None = None
    count: int = 0
    last: str = "-"
    values: dict[str, Any] | None = None
    last_at: float | None = None
    first_at: float = 0.0
    priority: int | None = None
    publishers: set[str] = field(default_factory=set)
    #: events per whole second, the last ``WINDOW`` + 1 seconds: a rate in bounded memory
    seconds: collections.deque[list[int]] = field(default_factory=collections.deque)
    history: collections.deque[tuple[float, dict[str, float]]] = field(
        default_factory=lambda: collections.deque(maxlen=HISTORY)
    )


@dataclass
class _Node:
    key: str
    txnode: int | None = None
    name: str | None = None
    address: str | None = None
    alive: bool = True
    last_heard: float | None = None


class Live:
    """What is known of a network right now."""

    def __init__(self, catalog: Catalog, network: str, source: str, bitrate: int = 500_000):
        self.catalog = catalog
        self.network = network  #: "can" or "tcp"
        self.source = source  #: the bus or the TCP-ECB's address
        self.bitrate = bitrate
        self.channels: dict[str, _Channel] = {}
        self.nodes: dict[str, _Node] = {}
        self.recent: collections.deque[str] = collections.deque(maxlen=RECENT)
        self.jaus: dict[str, dict[str, Any]] = {}  #: node key -> its JAUS component's status
        self.counters = {"foreign": 0, "malformed": 0, "dropped": 0, "untracked": 0,
                         "status_failures": 0}  # fmt: skip
        self._bits: collections.deque[list[int]] = collections.deque()  #: [second, bits]
        self._began: float | None = None  #: the first frame's time

    # --- feeding ----------------------------------------------------------------------------

    def event(
        self, now: float, uid: int | None, etag: int | None, sender: str, priority: int,
        data: bytes,
    ) -> None:  # fmt: skip
        """One event, heard from ``sender`` (a TxNode or node id, as text)."""
        key = f"0x{uid:016x}" if uid is not None else f"etag 0x{etag or 0:04x}"
        chan = self.channels.get(key)
        if chan is None:
            if len(self.channels) >= MAX_CHANNELS:
                self.counters["untracked"] += 1
                return
            name = None if uid is None else self.catalog.channel(uid).name
            chan = self.channels[key] = _Channel(key, uid, name, etag, first_at=now)
        chan.count += 1
        chan.last_at = now
        if etag is not None:
            chan.etag = etag
        chan.priority = priority
        second = int(now)
        if chan.seconds and chan.seconds[-1][0] == second:
            chan.seconds[-1][1] += 1
        else:
            chan.seconds.append([second, 1])
            if len(chan.seconds) > WINDOW + 1:
                chan.seconds.popleft()
        if len(chan.publishers) < 64:
            chan.publishers.add(sender)
        if uid is not None:
            chan.last = self.catalog.format(uid, data)
            values = self.catalog.decode(uid, data)
            chan.values = None if values is None else {k: _jsonable(v) for k, v in values.items()}
            numbers = {k: float(v) for k, v in (values or {}).items()
                       if isinstance(v, int | float) and math.isfinite(float(v))}  # fmt: skip
            if numbers:
                chan.history.append((now, numbers))
        else:
            chan.last = data.hex() or "-"

    def known(self, uid: int, name: str | None = None, etag: int | None = None) -> None:
        """A channel that exists, with or without events yet: bound on the bus, or listed by
        the TCP-ECB. Its name from the catalog first, else ``name``."""
        key = f"0x{uid:016x}"
        chan = self.channels.get(key)
        if chan is None:
            if len(self.channels) >= MAX_CHANNELS:
                self.counters["untracked"] += 1
                return
            chan = self.channels[key] = _Channel(key, uid, self.catalog.channel(uid).name, etag,
                                                 first_at=time.time())  # fmt: skip
        if chan.name is None:
            chan.name = name
        if etag is not None:
            chan.etag = etag

    def node(self, now: float, key: str, **info: Any) -> None:
        """A node was heard of (joined, heard from, or listed by the TCP-ECB)."""
        node = self.nodes.get(key)
        if node is None:
            if len(self.nodes) >= MAX_NODES:
                self.counters["untracked"] += 1
                return
            node = self.nodes[key] = _Node(key)
            self.recent.append(f"{_clock(now)} joined: {_label(key, info)}")
        elif not node.alive:
            self.recent.append(f"{_clock(now)} back: {_label(key, info)}")
        for name, value in info.items():
            setattr(node, name, value)
        node.alive = True
        node.last_heard = now

    def left(self, now: float, key: str, why: str) -> None:
        node = self.nodes.get(key)
        if node is not None and node.alive:
            node.alive = False
            self.recent.append(f"{_clock(now)} {why}: {_label(key, {'name': node.name})}")

    def frame_bits(self, now: float, bits: int) -> None:
        if self._began is None:
            self._began = now
        second = int(now)
        if self._bits and self._bits[-1][0] == second:
            self._bits[-1][1] += bits
        else:
            self._bits.append([second, bits])
            if len(self._bits) > WINDOW + 1:
                self._bits.popleft()

    # --- reading ----------------------------------------------------------------------------

    def stats(self, now: float | None = None) -> dict[str, float | None]:
        """The counters, with what is tracked and the bus load (``ups console --metrics``)."""
        return {
            **self.counters,
            "events": sum(c.count for c in self.channels.values()),
            "channels": len(self.channels),
            "nodes": sum(1 for n in self.nodes.values() if n.alive),
            "jaus": len(self.jaus),
            "bus_load": self.bus_load(now),
        }

    def bus_load(self, now: float | None = None) -> float | None:
        """The share of the bus's bit rate its frames took in the last ``WINDOW`` s (CAN)."""
        if self.network != "can":
            return None
        now = time.time() if now is None else now
        return _per_second(self._bits, now, now if self._began is None else self._began) / (
            self.bitrate
        )

    def snapshot(self, now: float | None = None) -> dict[str, Any]:
        now = time.time() if now is None else now
        since = now - WINDOW
        for chan in self.channels.values():
            while chan.seconds and chan.seconds[0][0] < int(since):
                chan.seconds.popleft()
        while self._bits and self._bits[0][0] < int(since):
            self._bits.popleft()
        if self.network == "can":
            for node in self.nodes.values():
                if node.alive and node.last_heard is not None and now - node.last_heard > SILENT:
                    self.left(now, node.key, "silent")
        load = None
        if self.network == "can":
            first = now if self._began is None else self._began
            load = round(_per_second(self._bits, now, first) / self.bitrate, 4)
        return {
            "network": self.network,
            "source": self.source,
            "time": now,
            "bus_load": load,
            "counters": dict(self.counters),
            "channels": [
                {
                    "key": c.key,
                    "uid": None if c.uid is None else f"0x{c.uid:016x}",
                    "name": c.name,
                    "etag": None if c.etag is None else f"0x{c.etag:04x}",
                    "rate": round(_per_second(c.seconds, now, c.first_at), 1),
                    "count": c.count,
                    "last": c.last,
                    "values": c.values,
                    "age": None if c.last_at is None else round(now - c.last_at, 1),
                    "priority": c.priority,
                    "publishers": sorted(c.publishers),
                }
                for c in sorted(self.channels.values(), key=lambda c: (c.name or "~", c.key))
            ],
            "nodes": [
                {
                    "key": n.key,
                    "txnode": None if n.txnode is None else f"0x{n.txnode:02x}",
                    "name": n.name,
                    "address": n.address,
                    "alive": n.alive,
                }
                for n in sorted(self.nodes.values(), key=lambda n: n.key)
            ],
            "jaus": [
                {
                    "node": key,
                    "id": j.get("id"),
                    "state": j.get("state"),
                    "controller": j.get("controller"),
                    "clients": [
                        {k: c.get(k) for k in ("id", "address", "framing", "silent_s")}
                        for c in j.get("clients") or ()
                    ],
                }
                for key, j in sorted(self.jaus.items())
            ],
            "recent": list(self.recent),
        }

    def history(self, key: str) -> list[tuple[float, dict[str, float]]]:
        chan = self.channels.get(key)
        return [] if chan is None else list(chan.history)


def _per_second(buckets: collections.deque[list[int]], now: float, first: float) -> float:
    """The mean per second of the whole-second ``buckets`` in the window before ``now`` (or
    since ``first``, while the window is not yet full)."""
    start = math.ceil(now - WINDOW)
    total = sum(n for second, n in buckets if second >= start)
    return total / max(1.0, now - max(start, first))


def _jsonable(value: object) -> Any:
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _clock(now: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(now))


def _label(key: str, info: dict[str, Any]) -> str:
    return f"{info['name']} ({key})" if info.get("name") else key


# --- feeds ------------------------------------------------------------------------------------


async def feed_can(live: Live, bus: str, bindings: Bindings) -> None:
    """Listen to ``bus`` until cancelled; never send. python-can's ``recv`` blocks, so a
    thread reads and hands each frame to the loop."""
    import asyncio
    import threading

    import can

    from .._canlink import open_bus
    from .._errors import UpsError

    loop = asyncio.get_running_loop()
    stop = threading.Event()
    for etag, uid in bindings.etags.items():  # bound before: from the CAN-ECB's database
        live.known(uid, etag=etag)
    listener = open_bus(bus)

    pending: collections.deque[can.Message] = collections.deque()

    def drain() -> None:
        while pending:
            _can_frame(live, bindings, pending.popleft())

    def pump() -> None:  # frames wait in a bounded queue while the loop is busy
        while not stop.is_set():
            msg = listener.recv(0.2)
            if msg is None:
                continue
            if len(pending) >= MAX_PENDING:
                live.counters["dropped"] += 1
                continue
            pending.append(msg)
            if len(pending) == 1:  # the loop drains all there are, once woken
                loop.call_soon_threadsafe(drain)

    try:
        await asyncio.to_thread(pump)
    except can.CanError as exc:
        raise UpsError(f"the bus {bus} failed: {exc}") from None
    finally:
        stop.set()
        listener.shutdown()


def _can_frame(live: Live, bindings: Bindings, msg: can.Message) -> None:
    from .. import _canproto as p
    from .._bindings import Event
    from ..rt._frames import frame_bits

    now = time.time()
    if not msg.is_error_frame:  # every frame loads the bus, UPS or not
        size = 0 if msg.is_remote_frame else len(msg.data)
        id_bits = 29 if msg.is_extended_id else 11
        live.frame_bits(now, frame_bits(size, id_bits, "none", fd=bool(msg.is_fd)))
    if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
        live.counters["foreign"] += 1
        return
    item = bindings.read(msg.arbitration_id, bytes(msg.data), fd=bool(msg.is_fd), now=now)
    if item is None:
        live.counters["malformed"] += 1
    elif isinstance(item, Event):
        node_id = bindings.txnodes.get(item.txnode)
        key = f"0x{node_id:016x}" if node_id is not None else f"TxNode 0x{item.txnode:02x}"
        live.node(now, key, txnode=item.txnode)
        live.event(now, item.uid, item.etag, f"0x{item.txnode:02x}", item.priority, item.data)
    elif isinstance(item, p.Bind):
        live.known(item.uid, etag=item.etag)
    elif isinstance(item, p.Assign):
        live.nodes.pop(f"TxNode 0x{item.txnode:02x}", None)  # heard before its id was known
        live.node(now, f"0x{item.node_id:016x}", txnode=item.txnode)
    elif isinstance(item, p.Request | p.Holds | p.Declare):
        node_id = bindings.txnodes.get(item.txnode)
        if node_id is not None:
            live.node(now, f"0x{node_id:016x}", txnode=item.txnode)


async def feed_tcp(live: Live, node: Node, net: IpNetwork, channels: list[int]) -> None:
    """Follow the IP network ``net`` (TCP/IP or Zenoh) through ``node`` until cancelled: its
    nodes from its status (the TCP-ECB's, or on Zenoh every node's), every second; the events
    of ``channels`` (all listed, if empty)."""
    import asyncio

    from .._channel import Channel
    from .._errors import BrokerUnavailable

    who = "the TCP-ECB" if net.kind == "broker" else "the Zenoh network"

    subscribed: set[int] = set()
    if channels:
        await node.subscribe(*[Channel(u, live.catalog.channel(u).name) for u in channels],
                             maxlen=QUEUE)  # fmt: skip
        subscribed.update(channels)

    async def status() -> None:
        reachable = True
        while True:
            try:
                info = await net.status()
            except BrokerUnavailable as exc:  # it restarts, say: keep watching, and say so
                live.counters["status_failures"] += 1
                if reachable:
                    live.recent.append(f"{_clock(time.time())} no status from {who}: {exc}")
                reachable = False
                await asyncio.sleep(1.0)
                continue
            if not reachable:
                live.recent.append(f"{_clock(time.time())} {who} answers again")
            reachable = True
            now = time.time()
            listed = set()
            for n in info.get("nodes", ()):
                if n["node_id"] == f"0x{node.node_id:016x}":
                    continue  # ourselves
                listed.add(n["node_id"])
                if n.get("connected"):
                    live.node(now, n["node_id"], name=n.get("name"), address=n.get("address"))
                else:
                    live.left(now, n["node_id"], "disconnected")
            for key in list(live.nodes):
                if key not in listed:
                    live.left(now, key, "left")
            live.jaus = await _jaus_components(live, net, info.get("nodes", ()))
            for c in info.get("channels", ()):
                uid = int(c["uid"], 16)
                live.known(uid, c.get("name"))
                if not channels and uid not in subscribed and len(subscribed) < MAX_CHANNELS:
                    subscribed.add(uid)
                    name = live.catalog.channel(uid).name or c.get("name")
                    await node.subscribe(Channel(uid, name), maxlen=QUEUE)
            stats = node.stats()
            live.counters["dropped"] = stats.get("dropped", 0) + stats.get("lost", 0)
            await asyncio.sleep(1.0)

    poller = asyncio.create_task(status())
    try:
        while True:
            if poller.done():
                poller.result()  # the TCP-ECB went away: say so
            try:
                msg = await node.get_msg(timeout=1.0)
            except TimeoutError:
                continue
            source = "-" if msg.source is None else f"0x{msg.source:016x}"
            live.event(time.time(), msg.uid, None, source, msg.priority, msg.data)
            if msg.channel.name:
                live.known(msg.uid, msg.channel.name)
    finally:
        poller.cancel()
        await asyncio.gather(poller, return_exceptions=True)


async def _jaus_components(live: Live, net: IpNetwork, nodes: Any) -> dict[str, dict[str, Any]]:
    """The status of each JAUS component among ``nodes``: carried in the listing on Zenoh,
    asked of the nodes at their addresses on TCP/IP, all at once (at most ``MAX_JAUS``;
    failures counted)."""
    import asyncio

    from .._errors import UpsError

    components = [
        n for n in nodes if n.get("connected") and (n.get("name") == JAUS_NODE or "jaus" in n)
    ]
    live.counters["untracked"] += max(0, len(components) - MAX_JAUS)

    async def status_of(n: dict[str, Any]) -> Any:
        if "jaus" in n or net.kind != "broker" or not n.get("address"):
            return n.get("jaus")
        try:
            return (await net.node_status(n["address"])).get("jaus")
        except UpsError:
            live.counters["status_failures"] += 1
            return None

    found = components[:MAX_JAUS]
    answers = await asyncio.gather(*(status_of(n) for n in found))
    return {n["node_id"]: a for n, a in zip(found, answers, strict=True) if isinstance(a, dict)}
