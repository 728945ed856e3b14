"""eclipse-zenoh in peer mode, two sessions linked by one explicit TCP endpoint.

Both sessions run ``mode: peer`` with multicast and gossip scouting off; the listening side
(pong, sink) listens on ``tcp/127.0.0.1:ports[0]`` and the other side connects to it and
listens nowhere, so the two meet only there. Publishers are reliable with congestion
control BLOCK (a full queue makes ``put`` wait instead of dropping: zero loss).

Receiving: the pong echoes from inside its subscriber callback (run on a zenoh thread), the
sink counts in its callback, the ping reads its subscriber's FIFO channel.
``link.options["express"]`` (default False) sets the publishers' express flag (send at
once, never batch).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import threading
import time
from typing import Any

from ups.benchmarks.peers import STOP, Control, Link, SinkResult, seq
from ups.benchmarks.peers._common import Counter, probe_until_echoed

PING, PONG, DATA = "bench/ping", "bench/pong", "bench/data"
SETUP_TIMEOUT = 10.0


def missing(link: Link) -> str | None:
    """eclipse-zenoh, if it is not installed."""
    return None if importlib.util.find_spec("zenoh") else "eclipse-zenoh is not installed"


def describe(link: Link) -> str:
    """The zenoh version and the publisher settings."""
    express = "express" if link.options.get("express") else "batching allowed"
    return (f"eclipse-zenoh {importlib.metadata.version('eclipse-zenoh')}, reliable, "
            f"congestion BLOCK, {express}")  # fmt: skip


def _open(link: Link, listen: bool) -> Any:
    import zenoh

    endpoint = f'["tcp/{link.host}:{link.ports[0]}"]'
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("listen/endpoints", endpoint if listen else "[]")
    if not listen:
        conf.insert_json5("connect/endpoints", endpoint)
    return zenoh.open(conf)


def _publisher(session: Any, key: str, link: Link) -> Any:
    import zenoh

    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
        express=bool(link.options.get("express", False)),
    )


def _wait_matching(pub: Any) -> None:
    """Wait until a subscriber for ``pub``'s key is known on this side."""
    deadline = time.monotonic() + SETUP_TIMEOUT
    while not pub.matching_status:
        if time.monotonic() > deadline:
            raise TimeoutError(f"no subscriber for {pub.key_expr} within {SETUP_TIMEOUT} s")
        time.sleep(0.005)


def run_pong(link: Link, ctl: Control) -> None:
    """Listen; echo PING samples to PONG from the subscriber callback until STOP."""
    session = _open(link, listen=True)
    try:
        pub = _publisher(session, PONG, link)
        stopped = threading.Event()

        def echo(sample: Any) -> None:
            payload = sample.payload.to_bytes()
            pub.put(payload)
            if payload == STOP:
                stopped.set()

        session.declare_subscriber(PING, echo)
        ctl.ready()
        if not stopped.wait(600.0):
            raise TimeoutError("no STOP within 600 s")
    finally:
        session.close()


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Connect, probe until PING and PONG both route, then ping-pong; RTTs in seconds.

    Replies come through the subscriber's default FIFO channel, read with a blocking
    ``recv()`` in this thread (faster here than a callback handing over through a queue).
    That ``recv()`` has no timeout: the harness's deadline for the whole role bounds it.
    """
    session = _open(link, listen=False)
    try:
        replies = session.declare_subscriber(PONG)
        pub = _publisher(session, PING, link)
        _wait_matching(pub)

        def wait_echo(timeout: float) -> bytes | None:
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                sample = replies.try_recv()
                if sample is not None:
                    return bytes(sample.payload.to_bytes())
                time.sleep(0.001)
            return None

        probe_until_echoed(pub.put, wait_echo)
        rtts: list[float] = []
        clock = time.perf_counter
        for i in range(warmup + rounds):
            msg = seq(i)
            t0 = clock()
            pub.put(msg)
            while replies.recv().payload.to_bytes() != msg:  # a surplus probe's echo
                pass
            rtts.append(clock() - t0)
        pub.put(STOP)
        while replies.recv().payload.to_bytes() != STOP:
            pass
        return rtts[warmup:]
    finally:
        session.close()


def run_sink(link: Link, ctl: Control, count: int, idle_timeout: float) -> SinkResult:
    """Listen; count DATA samples in the callback until ``count`` arrived or it idles out."""
    session = _open(link, listen=True)
    try:
        counter = Counter(count, idle_timeout)
        done = threading.Event()

        def on_sample(_sample: Any) -> None:
            counter.add()
            if counter.done:
                done.set()

        session.declare_subscriber(DATA, on_sample)
        ctl.ready()
        while not counter.finished():
            done.wait(min(0.1, max(counter.remaining(), 1e-3)))
        return counter.result()
    finally:
        session.close()


def run_source(link: Link, ctl: Control, count: int) -> None:
    """Connect, wait for the sink's subscriber, ``put`` ``count`` samples, wait for release."""
    session = _open(link, listen=False)
    try:
        pub = _publisher(session, DATA, link)
        _wait_matching(pub)
        for i in range(count):
            pub.put(seq(i))
        ctl.wait_release()
    finally:
        session.close()
