"""Peers for ``benchmarks/tcp_compare.py``: one small module per transport, one interface.

A *peer module* (``benchmarks/peers/<name>.py``) implements four roles. Each role runs in
its own child process, started by the harness with the ``spawn`` method
(``benchmarks/peers/_child.py``). Where the measurement is pinned (round trips always,
throughput with ``--pin-throughput``) the child binds itself to the CPU
(``os.sched_setaffinity``) *before* it imports the peer module, so threads that the
library starts later (zmq I/O threads, zenoh's runtime) inherit the pin.
Import heavy libraries inside the role functions, not at module level: the harness imports
the module in the parent too, for ``describe``/``missing``/``service``.

Required functions (``link`` is a :class:`Link`, ``ctl`` a :class:`Control`):

``run_pong(link, ctl) -> None``
    Round-trip server. Set up (listen, subscribe, ...), call ``ctl.ready()`` once the
    pinger may start, then echo every 8-byte message back unchanged, including
    :data:`PROBE` messages. Return after echoing :data:`STOP`, or when the other side
    closes the connection.

``run_ping(link, ctl, warmup, rounds) -> list[float]``
    Round-trip client, started after the pong is ready. Send ``warmup + rounds`` messages
    ``seq(i)`` one at a time, each after the echo of the previous one arrived; ignore any
    echo that is not the one awaited (stale probes). Then send :data:`STOP` (so the pong
    returns) and return the ``rounds`` measured round trips in seconds
    (``time.perf_counter`` from before the send to after the echo), warm-up excluded.
    Transports that cannot tell when the path is open (pub/sub) first call
    :func:`benchmarks.peers._common.probe_until_echoed`.

``run_sink(link, ctl, count, idle_timeout) -> SinkResult``
    Throughput receiver. Set up, call ``ctl.ready()``, then count arriving messages until
    ``count`` have arrived, or until nothing arrived for ``idle_timeout`` seconds (the
    first message gets :data:`START_TIMEOUT`). Never stop early for any other reason:
    a lossy transport must show its loss in ``SinkResult.received``.

``run_source(link, ctl, count) -> None``
    Throughput sender, started after the sink is ready. Make sure the sink's subscription
    has reached this side (so no message is lost to a slow join), send ``seq(0..count-1)``
    as fast as the transport accepts them, then call ``ctl.wait_release()`` *before*
    closing anything (queued messages would otherwise be cut off), then clean up.

Optional functions, called in the parent process:

``describe(link) -> str``: a short note for the table (which loop, which sockets, ...).
``missing(link) -> str | None``: why the peer cannot run here (``None`` if it can).
``service(link, pin) -> contextlib.AbstractContextManager[None]``: infrastructure the two
sides need for one measurement, e.g. a broker listening on ``link.ports[0]``; ``pin`` is
the CPU the measurement is pinned to, or ``None``.

To add a peer: write the module, then add a :class:`PeerSpec` to :data:`PEERS` under the
name that ``--peers`` selects it by, e.g. ``"ups": [PeerSpec("UPS TCP", _P + "ups_tcp")]``.
An asyncio-based peer runs its own loop inside each role (see ``asyncio_msgpack.py``).
``raw_tcp.py`` is the smallest complete example.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

PAYLOAD_SIZE = 8
START_TIMEOUT = 20.0  # seconds a sink waits for its first message


@dataclass(frozen=True)
class Link:
    """Where and how the two sides of one measurement meet.

    ``ports``: free TCP ports on ``host`` reserved by the harness for this measurement
    (the listening side binds ``ports[0]``; a peer that needs a second port uses
    ``ports[1]``; for a brokered peer ``ports[0]`` is the broker's). ``options``: the
    per-variant settings from :attr:`PeerSpec.options`.
    """

    host: str
    ports: tuple[int, ...]
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SinkResult:
    """What a sink saw: messages received, and seconds from the first to the last one."""

    received: int
    seconds: float


class Control(Protocol):
    """A role's line back to the harness (see ``benchmarks/peers/_child.py``)."""

    def ready(self) -> None:
        """Tell the harness that the other side may start now."""

    def wait_release(self, timeout: float = 60.0) -> bool:
        """Block until the harness releases a source (its sink has reported); False on timeout."""


@dataclass(frozen=True)
class PeerSpec:
    """One row of the table: a peer module with its options.

    ``measure`` says which of ``"rtt"`` and ``"throughput"`` the row runs.
    """

    label: str
    module: str
    options: dict[str, Any] = field(default_factory=dict)
    measure: frozenset[str] = frozenset({"rtt", "throughput"})


def seq(i: int) -> bytes:
    """The 8-byte payload of message ``i``."""
    return i.to_bytes(PAYLOAD_SIZE, "little")


PROBE = b"\xfe" * PAYLOAD_SIZE  # path check before the measured round trips
STOP = b"\xff" * PAYLOAD_SIZE  # last message to a pong: echo it, then return

_P = "benchmarks.peers."
_ONE_WAY = frozenset({"throughput"})  # same path as another row's round trip: skip it
_MOSQUITTO_DEFAULT: dict[str, Any] = {"max_queued_messages": None}
PEERS: dict[str, list[PeerSpec]] = {
    "raw": [PeerSpec("raw TCP", _P + "raw_tcp")],
    "asyncio": [
        PeerSpec("asyncio+msgpack, stdlib loop", _P + "asyncio_msgpack", {"loop": "asyncio"}),
        PeerSpec("asyncio+msgpack, uvloop", _P + "asyncio_msgpack", {"loop": "uvloop"}),
    ],
    "zmq": [
        PeerSpec("pyzmq PUB/SUB, HWM=0", _P + "zmq_pubsub", {"hwm": 0}),
        PeerSpec("pyzmq PUB/SUB, default HWM", _P + "zmq_pubsub", {"hwm": None}, _ONE_WAY),
    ],
    "mqtt": [
        PeerSpec("paho-mqtt QoS 0 + mosquitto", _P + "mqtt_paho", {"max_queued_messages": 0}),
        PeerSpec("paho-mqtt QoS 0, default queue", _P + "mqtt_paho", _MOSQUITTO_DEFAULT, _ONE_WAY),
    ],
    "zenoh": [PeerSpec("zenoh peer-to-peer", _P + "zenoh_peer")],
    "ups": [
        PeerSpec("UPS TCP, uvloop", _P + "ups_tcp", {"loop": "uvloop"}),
        PeerSpec("UPS TCP, uvloop, compiled", _P + "ups_tcp", {"loop": "uvloop", "compiled": True}),
        PeerSpec("UPS TCP, stdlib loop", _P + "ups_tcp", {"loop": "asyncio"}),
    ],
}
