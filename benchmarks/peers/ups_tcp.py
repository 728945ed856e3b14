"""UPS itself on TCP/IP: ``ups.Node`` publishers and subscribers, a TCP-ECB per measurement.

The harness starts a TCP-ECB (``python -m upscli broker --recovery 0``) on
``127.0.0.1:ports[0]`` for each measurement (pinned with the round trip's processes; it is
not on the data path: it only tells publishers who subscribes) and stops it by PID
afterwards. Each role is one ``Node``; events go from the publishing node straight to the
subscribing node over the direct TCP link that the publisher dials (its frames coalesced
once per loop iteration), never through the ECB.

UPS's fast path, as an application that counts microseconds uses it (zenoh's peer uses its
callbacks too): callback subscriptions and ``publish_nowait`` on advertised channels.
Round trip: the pong subscribes ``bench/ping`` with a callback that publishes each event's
data back on ``bench/pong``; the ping subscribes ``bench/pong`` (``get_msg``: its task waits
for each echo) and, as every pub/sub peer here, probes until an echo comes back before it
measures. Throughput: the sink counts ``bench/data`` in a callback; the source publishes
probes until its link to the sink is up (the sink does not count them), then ``count``
events, yielding to the loop every :data:`YIELD_EVERY` publishes so the coalesced writes go
out. Queues are large enough that nothing is dropped (as zmq with HWM=0): the source's queue
to the sink holds ``count`` frames. ``link.options["loop"]`` picks ``"uvloop"`` or ``"asyncio"``
(the stdlib loop) for the roles; the broker runs on uvloop when it is installed.
``link.options["compiled"]``: the roles run the compiled UPS (``UPS_COMPILE=1``, see setup.py),
built by :mod:`benchmarks._compiled` into a copy of its own; a role checks that the compiled
modules are the ones it imported. The ECB is the same in both variants.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import importlib.util
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from typing import TYPE_CHECKING, Any

from ups.benchmarks._procs import process
from ups.benchmarks.peers import PROBE, STOP, Control, Link, SinkResult, seq
from ups.benchmarks.peers._common import Counter

if TYPE_CHECKING:
    from ups import Message, Node

PING, PONG, DATA = "bench/ping", "bench/pong", "bench/data"
SETUP_TIMEOUT = 10.0
IDLE_TIMEOUT = 30.0  # a pong that heard nothing for about this long gives up
YIELD_EVERY = 256  # a source publishes this many events between two yields to the loop
_READY = "TCP-ECB on "
# fixed node ids: no per-machine id slot (and its lock file) for the benchmark's nodes
PONG_ID, PING_ID, SINK_ID, SOURCE_ID = (0xBE7C_0000_0000_0000 + i for i in range(1, 5))


def missing(link: Link) -> str | None:
    """uvloop, when the variant asks for it and it is not installed; the compiled UPS, when
    asked for and it cannot be built (it is built here, before any role starts)."""
    if link.options.get("loop") == "uvloop" and importlib.util.find_spec("uvloop") is None:
        return "uvloop is not installed (scripts/bench-setup)"
    if link.options.get("compiled"):
        from ups.benchmarks import _compiled

        try:
            _compiled.build()
        except (RuntimeError, subprocess.SubprocessError) as exc:
            return str(exc).splitlines()[0]
    return None


def describe(link: Link) -> str:
    """The UPS version and the event loop the nodes run on."""
    version = importlib.metadata.version("ups-pubsub")
    if link.options.get("loop") == "uvloop":
        loop = f"uvloop {importlib.metadata.version('uvloop')}"
    else:
        loop = "stdlib asyncio loop"
    if link.options.get("compiled"):
        loop += f", compiled by mypyc {importlib.metadata.version('mypy')}"
    return f"ups {version}, {loop}, TCP-ECB + direct node links"


@contextlib.contextmanager
def service(link: Link, pin: int | None) -> Iterator[None]:
    """A TCP-ECB child process on ``link.ports[0]`` (pinned to ``pin``), stopped after."""
    listen = f"{link.host}:{link.ports[0]}"
    cmd = [sys.executable, "-m", "upscli", "broker", "--listen", listen, "--recovery", "0"]
    with process(cmd, _READY, pin=pin, timeout=SETUP_TIMEOUT):
        yield


def _run(link: Link, main: Callable[[], Coroutine[Any, Any, Any]]) -> Any:
    if link.options.get("loop") == "uvloop":
        import uvloop

        return uvloop.run(main())
    return asyncio.run(main())


def _node(link: Link, name: str, node_id: int, peer_queue: int = 1024) -> Node:
    from ups.benchmarks import _compiled

    compiled = _compiled.build() if link.options.get("compiled") else None
    node: Node = _compiled.import_ups(compiled).Node(
        broker=f"{link.host}:{link.ports[0]}",
        name=name,
        node_id=node_id,
        peer_queue=peer_queue,
        join_timeout=SETUP_TIMEOUT,
    )
    return node


async def _probe_until_echoed(
    send: Callable[[bytes], Awaitable[None]],
    wait_echo: Callable[[float], Awaitable[bytes | None]],
    timeout: float = SETUP_TIMEOUT,
    interval: float = 0.02,
) -> None:
    """:func:`benchmarks.peers._common.probe_until_echoed` for coroutines."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        await send(PROBE)
        if await wait_echo(interval) == PROBE:
            return
    raise TimeoutError(f"no echo of a probe within {timeout} s")


def run_pong(link: Link, ctl: Control) -> None:
    """Echo every ``bench/ping`` event on ``bench/pong`` until STOP (TimeoutError after
    about :data:`IDLE_TIMEOUT` seconds without one: pub/sub cannot see the ping leave)."""

    async def main() -> None:
        async with _node(link, "bench-pong", PONG_ID) as node:
            await node.advertise(PONG)
            loop = asyncio.get_running_loop()
            stopped = loop.create_future()
            publish = node.publish_nowait
            heard = [loop.time()]

            def echo(msg: Message) -> None:  # in the read callback: no task switch
                publish(PONG, msg.data)
                heard[0] = loop.time()
                if msg.data == STOP and not stopped.done():
                    stopped.set_result(None)

            await node.subscribe(PING, callback=echo)
            ctl.ready()
            while not stopped.done():  # up to IDLE_TIMEOUT without a ping: give up
                idle = loop.time() - heard[0]
                if idle > IDLE_TIMEOUT:
                    raise TimeoutError(f"no ping for {IDLE_TIMEOUT} s")
                await asyncio.wait([stopped], timeout=IDLE_TIMEOUT - idle)

    _run(link, main)


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Probe until the path is open, then ping-pong; the last ``rounds`` RTTs in seconds."""

    async def main() -> list[float]:
        async with _node(link, "bench-ping", PING_ID) as node:
            sub = await node.subscribe(PONG)
            await node.advertise(PING)
            publish_nowait, get_msg = node.publish_nowait, sub.get_msg

            async def publish(channel: str, data: bytes) -> None:
                publish_nowait(channel, data)

            async def wait_echo(t: float) -> bytes | None:
                try:
                    return (await get_msg(timeout=t)).data
                except TimeoutError:
                    return None

            await _probe_until_echoed(lambda m: publish(PING, m), wait_echo)
            rtts: list[float] = []
            clock = time.perf_counter
            # One deadline for the whole run: a timeout per get_msg would add its own cost.
            async with asyncio.timeout(SETUP_TIMEOUT + (warmup + rounds) * 1e-3):
                for i in range(warmup + rounds):
                    msg = seq(i)
                    t0 = clock()
                    publish_nowait(PING, msg)
                    while (await get_msg()).data != msg:  # a surplus probe's echo
                        pass
                    rtts.append(clock() - t0)
                publish_nowait(PING, STOP)
                while (await get_msg()).data != STOP:
                    pass
            return rtts[warmup:]

    result: list[float] = _run(link, main)
    return result


def run_sink(link: Link, ctl: Control, count: int, idle_timeout: float) -> SinkResult:
    """Count ``bench/data`` events (probes aside) in a callback subscription, as they arrive,
    until ``count`` or nothing came for a while."""

    async def main() -> SinkResult:
        counter = Counter(count, idle_timeout)
        async with _node(link, "bench-sink", SINK_ID) as node:
            loop = asyncio.get_running_loop()
            done = loop.create_future()
            add = counter.add

            def on_event(msg: Message) -> None:  # in the read callback: no queue, no task
                if msg.data != PROBE:
                    add()
                    if counter.done and not done.done():
                        done.set_result(None)

            await node.subscribe(DATA, callback=on_event)
            ctl.ready()
            while not counter.finished():
                await asyncio.wait([done], timeout=min(0.1, max(counter.remaining(), 1e-3)))
        return counter.result()

    result: SinkResult = _run(link, main)
    return result


def run_source(link: Link, ctl: Control, count: int) -> None:
    """Probe until the link to the sink is up, publish ``count`` events, wait for release."""

    async def main() -> None:
        async with _node(link, "bench-source", SOURCE_ID, peer_queue=count + 1024) as node:
            deadline = time.monotonic() + SETUP_TIMEOUT
            while True:  # the first publish registers us and brings the sink's address
                await node.publish(DATA, PROBE)
                if node.stats()["peers"] >= 1:
                    break
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no link to the sink within {SETUP_TIMEOUT} s")
                await asyncio.sleep(0.005)
            publish = node.publish_nowait
            for i in range(count):
                publish(DATA, seq(i))
                if i % YIELD_EVERY == YIELD_EVERY - 1:
                    await asyncio.sleep(0)  # let the coalesced writes go out
            await asyncio.to_thread(ctl.wait_release)  # a drop would show at the sink

    _run(link, main)
