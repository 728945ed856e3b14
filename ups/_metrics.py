"""``--metrics HOST:PORT``: a daemon's counters in Prometheus's text format, over HTTP.

Every daemon already counts what it does (its ``stats()``, which ``ups status`` shows). A
``MetricsServer`` reads those counters when Prometheus scrapes it, never in between: it keeps
no second count on the hot path. What it reads is described by tables of ``Metric``: a stable
name, a type, a help text and the stats key it comes from; docs/metrics.md lists them all
(tests/test_metrics.py keeps the two equal). The tables of the library's parts (a node, its
CAN link) are here; each daemon has its own beside it (``broker/_metrics.py``, ...).

Names: ``ups_<part>_<stats key>``, counters ending in ``_total``; gauges for sizes of tables
and queues. Labels only from bounded sets fixed in the code (``network``, ``direction``,
``daemon``, ``version``): never a node id, channel, address or identity, whose number has no
bound. Per-node and per-channel detail stays in ``ups status``.

Threads: the HTTP port is ``_metricsport.py``'s, in a thread of its own with its own event
loop: at most ``MAX_SCRAPES`` answers made at once, and fair admission (the status port's,
``ups/_port.py``): links that hold a slot past their turn give way to a newcomer, answered
links are closed. A scrape asks the daemon's event loop to read the counters (one callback: a
few dict lookups; scrapes that wait at once share one), so it never reads them while the loop
changes them, and waits at most ``SCRAPE_TIMEOUT`` for the answer (else 503). The loop never
waits for the server.

Imported by the ``ups`` command line for ``add_metrics``: prometheus-client and the rest
are imported only when a server starts.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import AsyncIterator, Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any, NamedTuple

from ._errors import ConfigError

if TYPE_CHECKING:
    import asyncio
    import concurrent.futures

    from ._metricsport import HttpPort

log = logging.getLogger("ups.metrics")

COUNTER, GAUGE = "counter", "gauge"
SCRAPE_TIMEOUT = 5.0  #: seconds a scrape waits for the event loop to read the counters
INSTALL = "--metrics needs prometheus-client: pip install 'ups-pubsub[metrics]'"


class Metric(NamedTuple):
    """One metric read from one stats dict: ``key``'s value, with ``labels`` fixed."""

    name: str  #: the full name (counters end in ``_total``)
    kind: str  #: COUNTER or GAUGE
    help: str
    key: str  #: the stats key it reads (a bool reads as 1 or 0; absent or None: no sample)
    labels: tuple[tuple[str, str], ...] = ()


def table(prefix: str, counters: Mapping[str, str], gauges: Mapping[str, str]) -> list[Metric]:
    """``prefix_KEY_total`` for each counter key, ``prefix_KEY`` for each gauge key."""
    made = [Metric(f"{prefix}_{key}_total", COUNTER, text, key) for key, text in counters.items()]
    return made + [Metric(f"{prefix}_{key}", GAUGE, text, key) for key, text in gauges.items()]


#: every daemon's: name, type, help; labels ``daemon`` (its command) and ``version``
BUILD_INFO = ("ups_build_info", GAUGE, "the UPS release and the daemon serving these metrics "
              "(always 1)", ("daemon", "version"))  # fmt: skip

#: What a daemon's ``read()`` returns (called on its event loop): each table with the stats
#: dict it reads and the labels its samples get (e.g. ``{"network": "can"}`` for a node's).
Reading = Sequence[tuple[Sequence[Metric], Mapping[str, Any], Mapping[str, str]]]


class Sample(NamedTuple):
    name: str
    kind: str
    help: str
    labels: tuple[tuple[str, str], ...]
    value: float


def samples(reading: Reading) -> list[Sample]:
    """The numbers of ``reading``, copied out of its stats dicts (on the event loop)."""
    found = []
    for metrics, stats, extra in reading:
        for m in metrics:
            value = stats.get(m.key)
            if isinstance(value, bool | int | float):
                labels = tuple(sorted((*m.labels, *extra.items())))
                found.append(Sample(m.name, m.kind, m.help, labels, float(value)))
    return found


# --- the library's tables ------------------------------------------------------------------

#: ``Node.stats()``, with ``network`` = can, tcp or zenoh: keys that a node on any network has,
#: then those of one kind of network (a node has only its own network's)
NODE = table(
    "ups_node",
    {
        "published": "events this node's applications published",
        "delivered": "events delivered to this node's subscriptions",
        "dropped": "events dropped because a subscription's queue was full",
        "callback_errors": "subscription callbacks that raised",
        "sent": "events sent onto the network (tcp: once per subscriber)",
        "received": "events received from the network (tcp, zenoh)",
        "lost": "events that never arrived, told by gaps in their publishers' numbers (tcp, zenoh)",
        "malformed": "frames or events that could not be decoded (can, tcp)",
        "foreign": "traffic that is not UPS: 11-bit and remote CAN frames, plain Zenoh "
        "samples (can, zenoh)",
        "unsubscribed": "events received for channels not subscribed (tcp, zenoh)",
        "too_large": "events too large for the channel's size class or buffer (can, zenoh)",
        "unknown": "CAN frames on etags whose binding this node never heard (can)",
        "filtered": "CAN frames of channels bound but not subscribed here, dropped in "
        "software (can)",
        "own_echo": "this node's own CAN frames heard back (can)",
        "rebinds": "bindings asked again after a contradiction (can)",
        "moves": "channels moved to a larger size class (can)",
        "reassigned": "Assigns of the TxNode this node held (a join under its id; can)",
        "unbound_dropped": "events dropped while their channel was being bound again (can)",
        "task_errors": "background tasks of the CAN face that failed (can)",
        "refused_large": "subscriptions refused: the channel's events exceed max_event (can)",
        "stray_verdicts": "Grants and Refuses for streams this node did not declare, ignored (can)",
        "refusals": "TxNodesFull, Failed, EtagsFull and Limit heard for this node's join or "
        "requests; each ends them only if it stands 3 s (can)",
        "stray_refusals": "EtagsFull, Failed and Limit naming a channel this node had bound "
        "already, ignored (can)",
        "large_lost": "multi-frame events given up in reassembly (can)",
        "large_frames_dropped": "frames of multi-frame events given up (can)",
        "reconnects": "reconnections to the TCP-ECB (tcp)",
        "denied": "registrations the TCP-ECB's ACL refused (tcp)",
        "unvouched": "events dropped: the TCP-ECB did not vouch for their publisher in time "
        "(tcp, TLS)",
        "impostors": "peers whose certificate did not match the node they claimed (tcp, TLS)",
        "peer_dropped": "events dropped for subscribers whose queues were full (tcp)",
        "status_builds": "status answers built (tcp)",
        "status_answers": "status requests answered (tcp)",
        "status_paced": "status requests that waited for the next build (tcp)",
        "status_denied": "status requests on the node's own links refused: the identity may "
        "not read it (tcp, TLS)",
        "receive_refused": "frames refused before their body was read: no room left in the "
        "receive buffers of the node's listening port (tcp)",
        "receive_stalled": "links from publishers closed for holding a grown receive buffer "
        "without completing a frame in time (tcp)",
        "unmatched": "events published while no subscriber was reached (zenoh)",
        "rx_overflow": "events dropped because the receive queue was full (zenoh)",
        "forgotten": "publishers no longer followed, to make room for others (zenoh)",
        "restarts": "publishers seen restarting their numbers (zenoh)",
        "sync_timeouts": "waits for the router's subscriber list that timed out (zenoh)",
        "pattern_refused": "channels a pattern subscription matched but could not join (an ACL, "
        "a bound)",
        "pattern_limited": "channels a pattern matched past the 4096 it may join",
    },
    {
        "bindings": "channels bound to an etag on the bus (can)",
        "txnode": "this node's TxNode on the bus, -1 before it joined (can)",
        "peers": "subscribers this node has a connection to (tcp)",
        "queued": "event frames queued to subscribers (tcp)",
        "broker_connected": "1 while connected to the TCP-ECB (tcp)",
        "receive_held": "bytes by which links from publishers grew their receive buffers (tcp)",
        "router_connected": "1 while connected to a Zenoh router (zenoh)",
        "rx_queued": "events received and not yet handed to subscriptions (zenoh)",
    },
)
#: what ``Node.stats()`` has and ``NODE`` leaves out, and why
NODE_UNEXPOSED = {"tx_failed": "the CAN link's, as ups_can_tx_failed_total"}

#: ``CanLink.stats()``: the one python-can bus of a daemon on CAN (shared by its parts)
CAN_LINK = table(
    "ups_can",
    {
        "rx_frames": "frames read from the bus (echoes of its own included)",
        "tx_frames": "frames the interface took",
        "tx_failed": "frames dropped: the interface refused them (bus off, queue full), or "
        "they waited too long, or found the backlog full",
        "backlog_full": "sends refused because the backlog had no room for them",
        "rx_errors": "errors reading the bus",
        "handler_errors": "received frames whose handler raised",
    },
    {"backlog": "frames of transfers waiting for room in the interface"},
)

#: every daemon's: the admission of its metrics port (``ups/_port.py``'s counters)
METRICS_PORT = table(
    "ups_metrics",
    {
        "answers": "scrapes answered (whatever the HTTP status)",
        "evicted": "connections closed because they held a slot past their turn (not sent a "
        "whole request, or not taken their answer, 0.5 s after) while others waited",
        "timed_out": "connections that did not send a whole request within 2 s of being let "
        "in, or were not answered within 10 s",
        "refused_busy": "connections closed unanswered: no slot came free in the 5 s they "
        "waited in line",
        "bad_requests": "connections that sent something else than an HTTP request (answered "
        "400 or 431)",
    },
    {},
)


# --- the server ----------------------------------------------------------------------------


def add_metrics(cmd: argparse.ArgumentParser) -> None:
    """The ``--metrics HOST:PORT`` option of a daemon."""
    cmd.add_argument(
        "--metrics", metavar="HOST:PORT", default=None,
        help="also serve the counters to Prometheus at http://HOST:PORT/metrics (:PORT for "
        "loopback; docs/metrics.md names them; default: not served)",
    )  # fmt: skip


def parse_metrics_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` or ``:PORT`` (loopback); the port is not optional."""
    from ._address import parse_address

    try:
        if ":" in text:
            return parse_address(text)
    except ConfigError:
        pass
    raise ConfigError(f"--metrics expects HOST:PORT (e.g. 127.0.0.1:9464), got {text!r}")


def check_metrics(address: str | None) -> None:
    """Refuse ``--metrics ADDRESS`` before a daemon starts anything: a bad address, or no
    prometheus-client (ConfigError, in one line)."""
    if address is None:
        return
    parse_metrics_address(address)
    try:
        import prometheus_client  # noqa: F401
    except ImportError:
        raise ConfigError(INSTALL) from None


@asynccontextmanager
async def serving_metrics(
    address: str | None, daemon: str, read: Callable[[], Reading]
) -> AsyncIterator[MetricsServer | None]:
    """Serve ``read()``'s metrics on ``address`` while in the block (nothing when None)."""
    if address is None:
        yield None
        return
    server = MetricsServer(address, daemon, read)
    await server.start()
    try:
        yield server
    finally:
        await server.close()


class MetricsServer:
    """Serves ``read()``'s metrics on ``address`` at ``/metrics`` (``port`` once started);
    ``daemon`` names the command in ``ups_build_info``."""

    def __init__(self, address: str, daemon: str, read: Callable[[], Reading]) -> None:
        check_metrics(address)
        self.host, self.port = parse_metrics_address(address)
        self.daemon = daemon
        self._read = read
        self._http: HttpPort | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/metrics"

    async def start(self) -> None:
        import asyncio

        from prometheus_client import CollectorRegistry, ProcessCollector

        from ._metricsport import HttpPort
        from ._port import listen

        try:
            sock = listen(self.host, self.port)
        except OSError as exc:
            raise ConfigError(
                f"cannot serve metrics on {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        self.port = sock.getsockname()[1]
        registry = CollectorRegistry(auto_describe=False)
        http = HttpPort(sock, _app(registry))
        loop = asyncio.get_running_loop()
        registry.register(_Collector(loop, self._read, self.daemon, lambda: http.counters))
        ProcessCollector(registry=registry)
        try:
            await http.start()
        except BaseException:
            sock.close()
            raise
        self._http = http
        log.info("metrics on %s", self.url)

    async def close(self) -> None:
        http, self._http = self._http, None
        if http is not None:
            await http.close()


class _Unavailable(Exception):
    """The daemon did not answer the scrape: 503."""


class _Collector:
    """Reads the daemon's counters on its event loop, once for the scrapes waiting together,
    and the metrics port's (``port()``) where it is."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        read: Callable[[], Reading],
        daemon: str,
        port: Callable[[], Mapping[str, int]],
    ) -> None:
        import threading
        from importlib.metadata import PackageNotFoundError, version

        self._loop = loop
        self._read = read
        self._port = port
        try:
            release = version("ups-pubsub")
        except PackageNotFoundError:
            release = "unknown"
        self._info = Sample(*BUILD_INFO[:3], (("daemon", daemon), ("version", release)), 1.0)
        self._lock = threading.Lock()
        self._reading: concurrent.futures.Future[list[Sample]] | None = None  # not read yet

    def collect(self) -> Iterator[Any]:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        families: dict[str, Any] = {}
        port = samples([(METRICS_PORT, self._port(), {})])
        for s in (self._info, *self._on_loop(), *port):
            family = families.get(s.name)
            if family is None:
                kind = CounterMetricFamily if s.kind == COUNTER else GaugeMetricFamily
                names = [name for name, _ in s.labels]
                family = families[s.name] = kind(s.name, s.help, labels=names)
            family.add_metric([value for _, value in s.labels], s.value)
        yield from families.values()

    def _on_loop(self) -> list[Sample]:
        """The daemon's samples, read on its loop after this scrape asked: a read that is
        asked for and not begun yet serves every scrape that comes meanwhile."""
        import concurrent.futures

        with self._lock:
            future = self._reading
            if future is None or future.done():
                future = self._reading = concurrent.futures.Future()
                try:
                    self._loop.call_soon_threadsafe(self._read_on_loop, future)
                except RuntimeError:  # the loop is closed: the daemon is stopping
                    raise _Unavailable("the daemon is stopping") from None
        try:
            return future.result(SCRAPE_TIMEOUT)
        except concurrent.futures.TimeoutError:
            raise _Unavailable(
                f"the daemon's event loop did not read its counters within {SCRAPE_TIMEOUT:g} s"
            ) from None

    def _read_on_loop(self, future: concurrent.futures.Future[list[Sample]]) -> None:
        with self._lock:  # begun: scrapes that come from now on ask for the next read
            if self._reading is future:
                self._reading = None
        try:
            future.set_result(samples(self._read()))
        except BaseException as exc:
            future.set_exception(exc)


def _app(registry: Any) -> Callable[[dict[str, Any], Callable[..., Any]], Iterable[bytes]]:
    """prometheus-client's WSGI app for ``registry``, at /metrics only; 503 when the daemon
    does not read its counters in time, 500 when its stats() fail."""
    from prometheus_client import make_wsgi_app

    metrics = make_wsgi_app(registry)

    def app(environ: dict[str, Any], start_response: Callable[..., Any]) -> Iterable[bytes]:
        if environ.get("PATH_INFO") not in ("/metrics", "/metrics/"):
            start_response("404 Not Found", [("Content-Type", "text/plain")])
            return [b"UPS metrics are at /metrics\n"]
        try:
            result: Iterable[bytes] = metrics(environ, start_response)
            return result
        except _Unavailable as exc:
            start_response("503 Service Unavailable", [("Content-Type", "text/plain")])
            return [f"{exc}\n".encode()]
        except Exception:  # a bug in a stats(): said once in the log, the daemon goes on
            log.exception("could not read the counters for a scrape")
            start_response("500 Internal Server Error", [("Content-Type", "text/plain")])
            return [b"could not read the counters (see the daemon's log)\n"]

    return app
