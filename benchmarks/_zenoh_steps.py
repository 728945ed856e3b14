"""The step roles of the Zenoh benchmark (``benchmarks/zenoh_face.py``), each spawned with a
pipe (:func:`step_main`): a ``source`` sends ``count`` events at a rate (or flat out) per step,
a ``sink`` counts each step's events (8 bytes: a number, the step), and the ``gateway``
(``_zenoh_gateway_role.py``) forwards frames a raw python-can bus sends it.

Every wait here is bounded; the harness kills a role that does not end by its PID.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import time
import traceback
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from typing import Any

from ups.benchmarks._zenoh_clients import (
    DATA,
    IDLE,
    PROBE_STEP,
    REPORT_LIMIT,
    TAG,
    TAIL_PAUSE,
    TICK,
    YIELD_EVERY,
    matched,
    pipe_recv,
    raw_matched,
    raw_publisher,
    raw_session,
    run,
    until,
    ups_node,
)
from ups.benchmarks._zenoh_gateway_role import gateway


def step_main(role: str, cfg: dict[str, Any], conn: Connection) -> None:
    """A spawned step role: ``role``'s function with its pipe; a failure goes up the pipe."""
    try:
        {"sink": sink, "source": source, "gateway": gateway}[role](cfg, conn)
    except BaseException:
        with contextlib.suppress(OSError):
            conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


class Tally:
    """Each step's events as a sink counts them: how many, first and last arrival."""

    def __init__(self) -> None:
        self.steps: dict[int, list[float]] = {}

    def add(self, data: bytes) -> None:
        if len(data) == TAG.size:
            now = time.perf_counter()
            st = self.steps.setdefault(TAG.unpack(data)[1], [0, now, now])
            st[0] += 1
            st[2] = now

    def done(self, step: int, count: int, started: float) -> bool:
        """All ``count`` arrived, or none for IDLE s, or the report waited REPORT_LIMIT s."""
        st = self.steps.get(step)
        now = time.perf_counter()
        if st is not None and st[0] >= count:
            return True
        last = max(started, st[2] if st is not None else started)
        return now - last > IDLE or now - started > REPORT_LIMIT

    def result(self, step: int) -> dict[str, float]:
        n, first, last = self.steps.pop(step, [0, 0.0, 0.0])
        return {"received": n, "seconds": last - first, "first": first, "last": last}


def sink(cfg: dict[str, Any], conn: Connection) -> None:
    """Count DATA events per step; ``("report", step, count)`` answers with the counts (and
    the node's counters: what it counted lost)."""
    tally = Tally()
    if cfg["kind"] == "raw":
        session = raw_session(cfg["endpoint"])
        try:
            add = tally.add
            key = cfg.get("key") or DATA
            session.declare_subscriber(key, lambda sample: add(sample.payload.to_bytes()))
            conn.send(("ready", None))
            while (cmd := pipe_recv(conn))[0] == "report":
                done = functools.partial(tally.done, cmd[1], cmd[2], time.perf_counter())
                while not done():
                    time.sleep(0.01)
                conn.send(("result", {**tally.result(cmd[1]), "stats": {}}))
        finally:
            session.close()
        return

    async def main() -> None:
        async with ups_node(cfg["kind"], cfg["endpoint"], "sink") as node:
            add = tally.add
            await node.subscribe(DATA, callback=lambda m: add(m.data))
            conn.send(("ready", None))
            while (cmd := await asyncio.to_thread(pipe_recv, conn))[0] == "report":
                done = functools.partial(tally.done, cmd[1], cmd[2], time.perf_counter())
                await until(done, "no report", 0.01)
                conn.send(("result", {**tally.result(cmd[1]), "stats": node.stats()}))

    run(main())


def _paced(step: int, count: int, rate: float, put: Callable[[bytes], Any]) -> Iterator[float]:
    """``put`` events 0 to ``count`` - 1 of ``step``: flat out (``rate`` 0), or what is due at
    ``rate`` each tick; yields the seconds to sleep (0: only let others run)."""
    clock, pack = time.perf_counter, TAG.pack
    start, i = clock(), 0
    while i < count:
        due = min(count, i + YIELD_EVERY if rate <= 0 else int((clock() - start) * rate) + 1)
        while i < due:
            put(pack(i, step))
            i += 1
        yield 0.0 if rate <= 0 else max(0.0, TICK - (clock() - start) % TICK)


def source(cfg: dict[str, Any], conn: Connection) -> None:
    """Wait until the sink matches; then, for each ``("run", step, rate, count)``, send
    ``count`` events of the step and answer how long it took."""
    if cfg["kind"] == "raw":
        session = raw_session(cfg["endpoint"])
        try:
            pub = raw_publisher(session, cfg.get("key") or DATA, cfg)
            raw_matched(pub)
            conn.send(("ready", None))
            while (cmd := pipe_recv(conn))[0] == "run":
                _, step, rate, count = cmd
                t0 = time.perf_counter()
                for pause in _paced(step, count, rate, pub.put):
                    if pause:
                        time.sleep(pause)
                conn.send(("done", {"sent": count, "seconds": time.perf_counter() - t0}))
        finally:
            session.close()
        return

    async def main() -> None:
        async with ups_node(cfg["kind"], cfg["endpoint"], "source") as node:
            await node.advertise(DATA)
            await until(matched(node, DATA), "no subscriber matched")
            conn.send(("ready", None))
            publish = node.publish_nowait
            while (cmd := await asyncio.to_thread(pipe_recv, conn))[0] == "run":
                _, step, rate, count = cmd
                t0 = time.perf_counter()
                for pause in _paced(step, count, rate, functools.partial(publish, DATA)):
                    await asyncio.sleep(pause)
                # A loss is counted from the gap before the next event: one more, uncounted,
                # after a pause, so that events lost at the step's end are counted in the step.
                await asyncio.sleep(TAIL_PAUSE)
                publish(DATA, TAG.pack(0, PROBE_STEP))
                conn.send(("done", {"sent": count, "seconds": time.perf_counter() - t0,
                                    "stats": node.stats()}))  # fmt: skip

    run(main())
