"""``ups console``: the paper's operator palmtop, today: a web page of the live network.

The page (``console.html``, plain JavaScript, nothing fetched from the internet) shows the
channels and nodes as ``ups monitor`` does, updated by server-sent events, a plot of a
chosen channel's decoded fields, and a form that publishes on a channel (hex, or
``field=value,...`` that the catalog encodes). Routes:

- ``GET /``: the page, which asks for ``GET /snapshot`` (one ``snapshot``, see ``_live``, as
  JSON) every ``SNAPSHOT_EVERY`` s; ``GET /events``: one per ``--snapshot-every`` s as
  server-sent events, for scripts;
- ``GET /history?key=0x...``: the channel's recent (time, values) points;
- ``POST /publish`` (JSON ``{"channel", "data"}``): ``{"ok": true}`` or ``{"error": "..."}``
  (400 for bad input, 403 when the TCP-ECB's ACL refuses), never a traceback.

With the TLS options the console is one more participant of the fleet: its node joins with
that identity (so the TCP-ECB's ACL decides what it may see and publish), and the page is
served over HTTPS to browsers that show a certificate of the same fleet CA. On CAN the
console listens only, and joins the bus the first time someone publishes from the page.

Bounds, each counted and logged when it bites (``_webguard``): requests whose Host is not
this console's (DNS rebinding: ``wrong_host``, 421) or posts from another site's page
(``cross_site``, 403); a connection that does not deliver a whole request within
``--header-timeout`` s (``HEADER_TIMEOUT`` by default; ``slow_requests``); live streams beyond
``MAX_PAGES_PER_CLIENT`` per client address or ``MAX_PAGES`` in all (``pages_refused``, 429
or 503), and streams whose reader fell ``PAGE_BACKLOG`` snapshots behind or let a write wait
``WRITE_TIMEOUT`` s (``pages_dropped``). The page itself holds no stream: nothing a client
holds shuts it out.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from .._cliargs import (
    add_catalog,
    add_network,
    add_tls,
    positive_float,
    positive_int,
    run_until_signal,
    say,
    tls_of,
)
from .._errors import ConfigError
from .._metrics import NODE, Metric, Reading, add_metrics, serving_metrics, table
from ._net import IpNetwork, network_of
from ._webguard import (
    HEADER_TIMEOUT,
    Notes,
    RequestClock,
    abort,
    allowed_names,
    backlog,
    host_allowed,
)


def _middleware(function: Any) -> Any:
    """aiohttp's middleware mark, without importing aiohttp for ``ups --help``."""
    function.__middleware_version__ = 1
    return function


log = logging.getLogger("ups.console")

HELP = "a web page of the live network: channels, nodes, a plot, a form to publish"
DEFAULT_LISTEN = "127.0.0.1:8470"
SNAPSHOT_EVERY = 0.5  #: seconds between snapshots sent to each page
MAX_PAGES = 32  #: live streams (GET /events) at once; more are answered 503
MAX_PAGES_PER_CLIENT = 4  #: live streams of one client address at once; more are answered 429
PAGE_BACKLOG = 10  #: snapshots a stream's reader may leave unread (5 s) before it is let go
WRITE_TIMEOUT = 5.0  #: seconds a stream's write may wait for its reader before it is let go
GUARD_COUNTERS = {
    "wrong_host": "requests refused: a Host that is not this console's (DNS rebinding)",
    "cross_site": "posts refused: from another site's page (Origin)",
    "slow_requests": "connections closed: no whole request within the header timeout",
    "pages_refused": "live streams refused: too many of the client's, or in all",
    "pages_dropped": "live streams dropped: their reader stopped reading",
}

#: ``Live.stats()``, with the pages open (``--metrics``; docs/metrics.md)
CONSOLE = table(
    "ups_console",
    {
        "events": "events seen on the channels tracked",
        "foreign": "frames that are not UPS (CAN)",
        "malformed": "UPS frames that could not be read (CAN)",
        "dropped": "events dropped: CAN frames the loop had no room for; on IP, the node's "
        "dropped and lost events",
        "untracked": "channels, nodes and JAUS components beyond the bounds, not tracked",
        "status_failures": "status requests that failed (TCP-ECB, Zenoh, JAUS components)",
        **GUARD_COUNTERS,
    },
    {
        "channels": "channels tracked",
        "nodes": "nodes tracked and alive",
        "jaus": "JAUS components shown",
        "pages": "live streams open (GET /events)",
        "bus_load": "share of the bus's bit rate its frames took in the last 5 s (CAN)",
    },
)


def add_arguments(cmd: argparse.ArgumentParser) -> None:
    cmd.add_argument(
        "--listen", default=DEFAULT_LISTEN, metavar="HOST:PORT",
        help=f"where the page is served (default {DEFAULT_LISTEN})",
    )  # fmt: skip
    cmd.add_argument(
        "--allow-host", action="append", default=None, metavar="NAME",
        help="a host name the page may be asked for (repeatable); besides it: localhost, the "
        "--listen host when a name, and any IP address; other names are refused (421), as a "
        "DNS-rebinding page would be",
    )  # fmt: skip
    add_network(cmd, "a CAN bus (listening; joins to publish)", "an IP network")
    cmd.add_argument("--db", default=None, help="CAN: the CAN-ECB's database (default: the bus's)")
    add_catalog(cmd)
    cmd.add_argument(
        "--bitrate", type=positive_int, default=500_000,
        help="CAN: the bus's bit rate, for its load (default 500000)",
    )  # fmt: skip
    cmd.add_argument("--timeout", type=positive_float, default=5.0, help="seconds to wait")
    cmd.add_argument(
        "--header-timeout", type=positive_float, default=HEADER_TIMEOUT, metavar="S",
        help=f"seconds a connection has to deliver a whole request (default {HEADER_TIMEOUT:g})",
    )  # fmt: skip
    cmd.add_argument(
        "--snapshot-every", type=positive_float, default=SNAPSHOT_EVERY, metavar="S",
        help=f"seconds between two snapshots of a live stream, GET /events (default "
        f"{SNAPSHOT_EVERY:g})",
    )  # fmt: skip
    add_tls(cmd, node=True)
    add_metrics(cmd)


def run(args: argparse.Namespace) -> int:
    from .._address import parse_address
    from .._bindings import Bindings
    from .._catalog import load_catalog
    from .._extras import require
    from ._live import Live

    require("aiohttp", "tools", "ups console needs aiohttp, which is not installed")
    host, port = parse_address(args.listen)
    can, net = network_of(args)
    live = Live(load_catalog(args.catalog), net.label if net else "can", can or str(net),
                args.bitrate)  # fmt: skip
    bindings = Bindings()
    if can is not None:
        bindings.load_bus_db(can, args.db)
    return run_until_signal(_serve(args, live, bindings, can, net, host, port))


async def _serve(
    args: argparse.Namespace, live: Any, bindings: Any, can: str | None, net: IpNetwork | None,
    host: str, port: int,
) -> int:  # fmt: skip
    import asyncio
    import contextlib

    from aiohttp import web

    from .._node import Node
    from ._live import feed_can, feed_tcp

    tls = tls_of(args)
    node: Node | None = None
    joining = asyncio.Lock()

    async def publisher() -> Node:  # on CAN, the console joins when first asked to publish
        nonlocal node
        async with joining:
            if node is None:
                node = Node(can=can, name="ups-console", join_timeout=args.timeout)
                await node.start()
        return node

    app = web.Application(client_max_size=64 * 1024, middlewares=[_guard])
    app["live"], app["publisher"], app["pages"] = live, publisher, 0
    app["streams"] = set()  # the tasks serving /events: ended at once on shutdown
    app["per_client"] = {}  # client address -> its live streams open
    app["names"] = allowed_names(host, args.allow_host)  # Host names served (and addresses)
    app["counters"] = dict.fromkeys(GUARD_COUNTERS, 0)
    app["notes"] = notes = Notes(app["counters"])
    app["header_timeout"], app["snapshot_every"] = args.header_timeout, args.snapshot_every
    app["clock"] = clock = RequestClock(args.header_timeout, notes)
    app.add_routes([
        web.get("/", _page), web.get("/events", _events), web.get("/snapshot", _snapshot),
        web.get("/history", _history), web.post("/publish", _publish),
    ])  # fmt: skip

    def reading() -> Reading:
        readings: list[tuple[list[Metric], dict[str, Any], dict[str, str]]] = [
            (CONSOLE, {**live.stats(), **app["counters"], "pages": app["pages"]}, {})
        ]
        if node is not None:  # on IP at once; on CAN once the page published
            network = "can" if net is None else net.label
            readings.append((NODE, dict(node.stats()), {"network": network}))
        return readings

    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    server: asyncio.Server | None = None
    try:
        async with serving_metrics(args.metrics, "console", reading) as metrics:
            if metrics is not None:
                say(args, f"metrics on {metrics.url}")
            server = await asyncio.get_running_loop().create_server(  # each connection timed
                clock.protocol_factory(runner.server), host or None, port, ssl=_https(tls),
                reuse_address=True,
            )  # fmt: skip
            scheme = "https" if tls is not None else "http"
            bound = server.sockets[0].getsockname()[1]  # the port, when --listen asked for any
            if net is not None:  # the page is served first: a port in use is said at once
                node = net.node("ups-console")
                await node.start()
            say(args, f"console on {scheme}://{host}:{bound}")
            if can is not None:
                await feed_can(live, can, bindings)
            else:
                assert node is not None and net is not None
                await feed_tcp(live, node, net, [])
    except asyncio.CancelledError:
        pass  # Ctrl-C, SIGTERM: the way to stop it
    finally:
        if server is not None:
            server.close()
        for stream in list(app["streams"]):  # open pages would hold shutdown for minutes
            stream.cancel()
        await runner.cleanup()
        clock.close()
        log.info("console stopping: %s", app["counters"])
        if node is not None:
            with contextlib.suppress(Exception):
                await node.close()
    return 0


@_middleware
async def _guard(request: Any, handler: Any) -> Any:
    """Refuse requests for a host name not this console's (DNS rebinding: a page of
    another site whose name now resolves here), and cross-site posts: a POST must come from
    this console's own page (Origin, when a browser sends one). Times each connection's
    requests (``RequestClock``)."""
    from aiohttp import web

    app, clock = request.app, request.app["clock"]
    clock.begin(request.protocol)
    try:
        if not host_allowed(request.host, app["names"]):
            app["notes"]("wrong_host", "request from %s for %r refused: not this console's "
                         "name (--allow-host)", request.remote, request.host)  # fmt: skip
            return web.json_response({"error": f"not this console: {request.host}"}, status=421)
        origin = request.headers.get("Origin")
        if request.method == "POST" and origin and origin.split("://", 1)[-1] != request.host:
            app["notes"]("cross_site", "post from %s refused: from the page of %s",
                         request.remote, origin)  # fmt: skip
            return web.json_response({"error": f"not from this console's page: {origin}"},
                                     status=403)  # fmt: skip
        return await handler(request)
    finally:
        clock.end(request.protocol)


def _https(tls: Any) -> Any:
    """The server's TLS context: the fleet certificate, and a browser's of the same CA."""
    if tls is None:
        return None
    import ssl

    context = tls.server()
    context.verify_mode = ssl.CERT_REQUIRED
    return context


async def _page(request: Any) -> Any:
    from importlib.resources import files

    from aiohttp import web

    html = files("ups.tools").joinpath("console.html").read_text(encoding="utf-8")
    return web.Response(text=html, content_type="text/html")


async def _snapshot(request: Any) -> Any:
    from aiohttp import web

    return web.json_response(request.app["live"].snapshot())


async def _events(request: Any) -> Any:
    import asyncio
    import collections
    import json

    from aiohttp import web

    app, client = request.app, request.remote or "?"
    per_client = app["per_client"]
    mine = per_client.get(client, 0)
    if mine >= MAX_PAGES_PER_CLIENT or app["pages"] >= MAX_PAGES:
        app["notes"]("pages_refused", "live stream of %s refused: %d of its own open, %d in all",
                     client, mine, app["pages"])  # fmt: skip
        if mine >= MAX_PAGES_PER_CLIENT:
            text = f"at most {MAX_PAGES_PER_CLIENT} live streams per client"
            return web.Response(status=429, text=text)
        return web.Response(status=503, text=f"at most {MAX_PAGES} live streams at once")
    app["pages"] += 1
    per_client[client] = mine + 1
    app["streams"].add(asyncio.current_task())
    sent: collections.deque[int] = collections.deque(maxlen=PAGE_BACKLOG)
    try:
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                               "Cache-Control": "no-cache"})  # fmt: skip
        await response.prepare(request)
        while True:
            data = f"data: {json.dumps(app['live'].snapshot())}\n\n".encode()
            async with asyncio.timeout(WRITE_TIMEOUT):  # a write its reader holds up: let go
                await response.write(data)
            sent.append(len(data))
            behind = backlog(request.transport) if request.transport is not None else None
            if behind is not None and len(sent) == PAGE_BACKLOG and behind > sum(sent):
                app["notes"]("pages_dropped", "live stream of %s dropped: %d bytes unread, "
                             "over %d snapshots", client, behind, PAGE_BACKLOG)  # fmt: skip
                abort(request.transport)
                return response
            await asyncio.sleep(app["snapshot_every"])
    except TimeoutError:
        app["notes"]("pages_dropped", "live stream of %s dropped: a write waited %g s",
                     client, WRITE_TIMEOUT)  # fmt: skip
        abort(request.transport)
        return response
    except ConnectionError:
        return response  # the reader went away
    finally:
        app["pages"] -= 1
        per_client[client] -= 1
        if not per_client[client]:
            del per_client[client]
        app["streams"].discard(asyncio.current_task())


async def _history(request: Any) -> Any:
    from aiohttp import web

    points = request.app["live"].history(request.query.get("key", ""))
    return web.json_response([{"t": t, "values": v} for t, v in points])


async def _publish(request: Any) -> Any:
    import asyncio

    from aiohttp import web

    from .._channel import parse_channel
    from .._errors import AccessDenied, UpsError

    if request.content_type != "application/json":  # a form another site posts is not JSON:
        return web.json_response(  # browsers send JSON across sites only after asking
            {"error": "send JSON (Content-Type: application/json)"}, status=415
        )
    try:
        async with asyncio.timeout(request.app["header_timeout"]):  # a body trickled in: let go
            body = await request.json()
        if not isinstance(body, dict):
            raise ConfigError("the body must be a JSON object with channel and data")
        channel = parse_channel(str(body["channel"]).strip())
        data = request.app["live"].catalog.payload(channel, str(body.get("data", "")))
        node = await request.app["publisher"]()
        await node.publish(channel, data)
    except TimeoutError:
        request.app["notes"]("slow_requests", "post from %s: its body did not arrive within %g s",
                             request.remote, request.app["header_timeout"])  # fmt: skip
        return web.json_response({"error": "the body came too slowly"}, status=408)
    except AccessDenied as exc:
        return web.json_response({"error": str(exc)}, status=403)
    except (UpsError, ValueError, KeyError) as exc:
        text = str(exc) if isinstance(exc, UpsError | ValueError) else f"missing {exc}"
        return web.json_response({"error": text}, status=400)
    return web.json_response({"ok": True, "channel": str(channel), "data": data.hex()})
