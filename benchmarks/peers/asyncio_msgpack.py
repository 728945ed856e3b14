"""A hand-written baseline: asyncio ``BufferedProtocol`` over TCP, each message msgpack-framed.

Every 8-byte payload travels as one msgpack ``bin 8`` object (10 bytes on the wire); the
receiver feeds what arrives into a streaming ``msgpack.Unpacker``. TCP_NODELAY is on (asyncio
sets it on TCP transports). ``link.options["loop"]`` picks ``"asyncio"`` (the stdlib loop)
or ``"uvloop"``.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import importlib.util
import time
from collections.abc import Callable, Coroutine
from typing import Any, cast

from ups.benchmarks.peers import STOP, Control, Link, SinkResult, seq
from ups.benchmarks.peers._common import Counter

BUFFER_SIZE = 1 << 16


def missing(link: Link) -> str | None:
    """uvloop, when the variant asks for it and it is not installed."""
    if link.options.get("loop") == "uvloop" and importlib.util.find_spec("uvloop") is None:
        return "uvloop is not installed (scripts/bench-setup)"
    return None


def describe(link: Link) -> str:
    """Which event loop the variant runs on."""
    if link.options.get("loop") == "uvloop":
        return f"uvloop {importlib.metadata.version('uvloop')}, msgpack bin frames"
    return "stdlib asyncio loop, msgpack bin frames"


def _run(link: Link, main: Callable[[], Coroutine[Any, Any, Any]]) -> Any:
    if link.options.get("loop") == "uvloop":
        import uvloop

        return uvloop.run(main())
    return asyncio.run(main())


class _Framed(asyncio.BufferedProtocol):
    """Receives msgpack objects into one reused buffer; ``on_message`` gets each payload."""

    def __init__(self, on_message: Callable[[bytes], None]) -> None:
        import msgpack

        self._buf = bytearray(BUFFER_SIZE)
        self._view = memoryview(self._buf)
        self._unpacker = msgpack.Unpacker()
        self._on_message = on_message
        self.transport: asyncio.Transport | None = None
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._writable = asyncio.Event()
        self._writable.set()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # uvloop's is no subclass

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._view

    def buffer_updated(self, nbytes: int) -> None:
        self._unpacker.feed(self._view[:nbytes])
        for obj in self._unpacker:
            self._on_message(obj)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)

    def pause_writing(self) -> None:
        self._writable.clear()

    def resume_writing(self) -> None:
        self._writable.set()

    @property
    def paused(self) -> bool:
        """True while the transport asks the writer to wait."""
        return not self._writable.is_set()

    async def writable(self) -> None:
        """Return once the transport's write buffer is below its high-water mark."""
        await self._writable.wait()


def run_pong(link: Link, ctl: Control) -> None:
    """Echo every message back, msgpack-framed, until STOP or the connection closes."""

    async def main() -> None:
        import msgpack

        packer = msgpack.Packer()
        done = asyncio.Event()

        def factory() -> _Framed:
            def echo(payload: bytes) -> None:
                assert proto.transport is not None
                proto.transport.write(packer.pack(payload))
                if payload == STOP:
                    done.set()

            proto = _Framed(echo)
            proto.closed.add_done_callback(lambda _f: done.set())
            return proto

        server = await asyncio.get_running_loop().create_server(
            factory, link.host, link.ports[0], reuse_address=True
        )
        async with server:
            ctl.ready()
            await done.wait()

    _run(link, main)


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Ping-pong ``warmup + rounds`` messages; return the last ``rounds`` RTTs in seconds."""

    async def main() -> list[float]:
        import msgpack

        loop = asyncio.get_running_loop()
        packer = msgpack.Packer()
        waiter: asyncio.Future[bytes] | None = None

        def on_reply(payload: bytes) -> None:
            if waiter is not None and not waiter.done():
                waiter.set_result(payload)

        transport, _ = await loop.create_connection(
            lambda: _Framed(on_reply), link.host, link.ports[0]
        )
        rtts: list[float] = []
        clock = time.perf_counter
        try:
            # One deadline for the whole run: a wait_for per round would add its own cost.
            async with asyncio.timeout(10.0 + (warmup + rounds) * 1e-3):
                for i in range(warmup + rounds):
                    msg = seq(i)
                    waiter = loop.create_future()
                    t0 = clock()
                    transport.write(packer.pack(msg))
                    reply = await waiter
                    rtts.append(clock() - t0)
                    if reply != msg:
                        raise RuntimeError(f"round {i}: echo {reply!r} != {msg!r}")
                waiter = loop.create_future()
                transport.write(packer.pack(STOP))
                await waiter
        finally:
            transport.close()
        return rtts[warmup:]

    result: list[float] = _run(link, main)
    return result


def run_sink(link: Link, ctl: Control, count: int, idle_timeout: float) -> SinkResult:
    """Count messages until ``count`` arrived, the source closed, or the sink idled out."""

    async def main() -> SinkResult:
        counter = Counter(count, idle_timeout)
        done = asyncio.Event()

        def on_message(_payload: bytes) -> None:
            counter.add()
            if counter.done:
                done.set()

        def factory() -> _Framed:
            proto = _Framed(on_message)
            proto.closed.add_done_callback(lambda _f: done.set())
            return proto

        server = await asyncio.get_running_loop().create_server(
            factory, link.host, link.ports[0], reuse_address=True
        )
        async with server:
            ctl.ready()
            while not done.is_set() and not counter.finished():
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(done.wait(), max(counter.remaining(), 1e-3))
        return counter.result()

    result: SinkResult = _run(link, main)
    return result


def run_source(link: Link, ctl: Control, count: int) -> None:
    """Write ``count`` framed messages, waiting whenever the transport pauses writing."""

    async def main() -> None:
        import msgpack

        loop = asyncio.get_running_loop()
        packer = msgpack.Packer()
        transport, proto = await loop.create_connection(
            lambda: _Framed(lambda _p: None), link.host, link.ports[0]
        )
        try:
            for i in range(count):
                transport.write(packer.pack(seq(i)))
                if proto.paused:
                    await proto.writable()
            await asyncio.to_thread(ctl.wait_release)
        finally:
            transport.close()

    _run(link, main)
