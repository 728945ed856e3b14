"""The round-trip roles of the Zenoh benchmark, a peer module of ``benchmarks/peers`` (run by
``tcp_compare.measure_rtt``): ``run_pong`` echoes, ``run_ping`` times; ``service`` is the Zenoh
router (``ups zenoh-router``), pinned with them. ``kind`` in the options: ``ups``, a UPS node
on its Zenoh face (callback subscriptions and ``publish_nowait``), or a plain zenoh session.

Every wait here is bounded; the harness kills a role that does not end by its PID.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import sys
import threading
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from ups.benchmarks._procs import process
from ups.benchmarks._zenoh_clients import (
    PING,
    PONG,
    SETUP_TIMEOUT,
    matched,
    raw_matched,
    raw_publisher,
    raw_session,
    run,
    until,
    ups_node,
)
from ups.benchmarks.peers import PROBE, STOP, Control, Link, seq
from ups.benchmarks.peers._common import probe_until_echoed

if TYPE_CHECKING:
    from ups import Message


def endpoint_of(link: Link) -> str:
    return f"tcp/{link.host}:{link.ports[0]}"


def describe(link: Link) -> str:
    version = importlib.metadata.version("eclipse-zenoh")
    if link.options.get("kind") == "ups":
        return f"ups {importlib.metadata.version('ups-pubsub')} Zenoh face, uvloop, zenoh {version}"
    congestion = link.options.get("congestion", "drop").upper()
    return f"eclipse-zenoh {version} client sessions, reliable, congestion {congestion}"


@contextlib.contextmanager
def service(link: Link, pin: int | None) -> Iterator[None]:
    """``ups zenoh-router`` on ``link.ports[0]`` (every thread pinned to ``pin``), stopped
    after by its PID."""
    cmd = [sys.executable, "-m", "upscli", "zenoh-router", "--listen", endpoint_of(link)]
    with process(cmd, "Zenoh router", pin=pin):
        yield


def run_pong(link: Link, ctl: Control) -> None:
    """Echo every PING event on PONG until STOP."""
    if link.options.get("kind") != "ups":
        session = raw_session(endpoint_of(link))
        try:
            pub = raw_publisher(session, PONG, link.options)
            stopped = threading.Event()

            def echo(sample: Any) -> None:  # in a zenoh thread
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
        return

    async def main() -> None:
        async with ups_node("ups", endpoint_of(link), "pong") as node:
            await node.advertise(PONG)
            stopped = asyncio.get_running_loop().create_future()
            publish = node.publish_nowait

            def echo(msg: Message) -> None:  # in the face's hand-over from Zenoh's thread
                publish(PONG, msg.data)
                if msg.data == STOP and not stopped.done():
                    stopped.set_result(None)

            await node.subscribe(PING, callback=echo)
            ctl.ready()
            await asyncio.wait_for(stopped, 600.0)

    run(main())


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Wait until the pong's subscription matches, probe until an echo comes back, then
    ping-pong; the last ``rounds`` round trips in seconds."""
    if link.options.get("kind") != "ups":
        return _raw_ping(link, warmup, rounds)

    async def main() -> list[float]:
        async with ups_node("ups", endpoint_of(link), "ping") as node:
            sub = await node.subscribe(PONG)
            await node.advertise(PING)
            await until(matched(node, PING), "no subscriber matched")
            publish, get_msg = node.publish_nowait, sub.get_msg
            async with asyncio.timeout(SETUP_TIMEOUT):  # until the pong's publisher knows us
                while True:
                    publish(PING, PROBE)
                    with contextlib.suppress(TimeoutError):
                        if (await get_msg(timeout=0.02)).data == PROBE:
                            break
            rtts: list[float] = []
            clock = time.perf_counter
            async with asyncio.timeout(SETUP_TIMEOUT + (warmup + rounds) * 2e-3):
                for i in range(warmup + rounds):
                    msg = seq(i)
                    t0 = clock()
                    publish(PING, msg)
                    while (await get_msg()).data != msg:  # a surplus probe's echo
                        pass
                    rtts.append(clock() - t0)
                publish(PING, STOP)
                while (await get_msg()).data != STOP:
                    pass
            return rtts[warmup:]

    result: list[float] = run(main())
    return result


def _raw_ping(link: Link, warmup: int, rounds: int) -> list[float]:
    session = raw_session(endpoint_of(link))
    try:
        replies = session.declare_subscriber(PONG)
        pub = raw_publisher(session, PING, link.options)
        raw_matched(pub)

        def wait_echo(timeout: float) -> bytes | None:
            until = time.monotonic() + timeout
            while time.monotonic() < until:
                sample = replies.try_recv()
                if sample is not None:
                    return bytes(sample.payload.to_bytes())
                time.sleep(0.001)
            return None

        probe_until_echoed(pub.put, wait_echo)
        rtts: list[float] = []
        clock = time.perf_counter
        recv = replies.recv  # no timeout: the harness's deadline for the role bounds it
        for i in range(warmup + rounds):
            msg = seq(i)
            t0 = clock()
            pub.put(msg)
            while recv().payload.to_bytes() != msg:  # a surplus probe's echo
                pass
            rtts.append(clock() - t0)
        pub.put(STOP)
        while recv().payload.to_bytes() != STOP:
            pass
        return rtts[warmup:]
    finally:
        session.close()
