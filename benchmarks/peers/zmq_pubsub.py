"""pyzmq PUB/SUB over ``tcp://127.0.0.1``.

Round trip: a PUB/SUB pair each way (the pong's SUB binds ``ports[0]``, its PUB binds
``ports[1]``; the ping connects a PUB and a SUB to them), not REQ/REP. Throughput: the sink's
SUB binds, the source connects an XPUB (a PUB that also hands over subscriptions, so the
source sees when the sink has subscribed and loses nothing to a slow join).

``link.options["hwm"]``: the SNDHWM and RCVHWM of every socket; 0 means no limit (no
message is ever dropped), None leaves libzmq's default of 1000, where a PUB drops what does
not fit, so a fast source loses messages.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import time
from typing import Any

from ups.benchmarks.peers import STOP, Control, Link, SinkResult, seq
from ups.benchmarks.peers._common import Counter, probe_until_echoed

RECV_TIMEOUT_MS = 30_000  # bounds every blocking receive


def missing(link: Link) -> str | None:
    """pyzmq, if it is not installed."""
    return None if importlib.util.find_spec("zmq") else "pyzmq is not installed"


def describe(link: Link) -> str:
    """The HWM this variant runs with, and the pyzmq version."""
    hwm = link.options.get("hwm")
    limit = "no HWM limit (HWM=0)" if hwm == 0 else f"HWM={hwm or 'default 1000'}"
    return f"pyzmq {importlib.metadata.version('pyzmq')}, {limit}, PUB/SUB pair each way"


def _socket(ctx: Any, kind: int, link: Link) -> Any:
    import zmq

    sock = ctx.socket(kind)
    hwm = link.options.get("hwm")
    if hwm is not None:
        sock.setsockopt(zmq.SNDHWM, hwm)
        sock.setsockopt(zmq.RCVHWM, hwm)
    sock.setsockopt(zmq.RCVTIMEO, RECV_TIMEOUT_MS)
    sock.setsockopt(zmq.LINGER, 1000)
    if kind == zmq.SUB:
        sock.setsockopt(zmq.SUBSCRIBE, b"")
    return sock


def _addr(link: Link, index: int) -> str:
    return f"tcp://{link.host}:{link.ports[index]}"


def run_pong(link: Link, ctl: Control) -> None:
    """Echo from the SUB on ports[0] to the PUB on ports[1] until STOP."""
    import zmq

    ctx = zmq.Context()
    sub, pub = _socket(ctx, zmq.SUB, link), _socket(ctx, zmq.PUB, link)
    try:
        sub.bind(_addr(link, 0))
        pub.bind(_addr(link, 1))
        ctl.ready()
        while True:
            msg = sub.recv()
            pub.send(msg)
            if msg == STOP:
                return
    finally:
        sub.close()
        pub.close()
        ctx.term()


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Probe until the path is open, then ping-pong; the last ``rounds`` RTTs in seconds."""
    import zmq

    ctx = zmq.Context()
    pub, sub = _socket(ctx, zmq.PUB, link), _socket(ctx, zmq.SUB, link)
    try:
        pub.connect(_addr(link, 0))
        sub.connect(_addr(link, 1))
        probe_until_echoed(pub.send, lambda t: sub.recv() if sub.poll(t * 1000) else None)
        rtts: list[float] = []
        clock = time.perf_counter
        for i in range(warmup + rounds):
            msg = seq(i)
            t0 = clock()
            pub.send(msg)
            while sub.recv() != msg:  # a surplus probe's echo
                pass
            rtts.append(clock() - t0)
        pub.send(STOP)
        while sub.recv() != STOP:
            pass
        return rtts[warmup:]
    finally:
        pub.close()
        sub.close()
        ctx.term()


def run_sink(link: Link, ctl: Control, count: int, idle_timeout: float) -> SinkResult:
    """SUB binds ports[0]; count until ``count`` arrived or nothing came for a while."""
    import zmq

    ctx = zmq.Context()
    sub = _socket(ctx, zmq.SUB, link)
    counter = Counter(count, idle_timeout)
    try:
        sub.bind(_addr(link, 0))
        ctl.ready()
        while not counter.finished():
            if not sub.poll(max(1, int(counter.remaining() * 1000))):
                continue
            while not counter.done:
                try:
                    sub.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
                counter.add()
        return counter.result()
    finally:
        sub.close(linger=0)
        ctx.term()


def run_source(link: Link, ctl: Control, count: int) -> None:
    """XPUB connects to ports[0], waits for the sink's subscription, then sends ``count``."""
    import zmq

    ctx = zmq.Context()
    pub = _socket(ctx, zmq.XPUB, link)
    try:
        pub.connect(_addr(link, 0))
        if not pub.poll(RECV_TIMEOUT_MS) or pub.recv()[:1] != b"\x01":
            raise TimeoutError("the sink's subscription did not arrive")
        for i in range(count):
            pub.send(seq(i))
        ctl.wait_release()
    finally:
        pub.close(linger=0)
        ctx.term()
