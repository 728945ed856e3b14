"""The roles of ``benchmarks/zenoh_face.py``, each run in a process of its own (spawned).

Two kinds of Zenoh client meet through a Zenoh router (``ups zenoh-router``, a process the
harness starts): ``ups``, a UPS node on its Zenoh face (``Node(zenoh=...)``, uvloop,
callback subscriptions and ``publish_nowait``); and ``raw``, a plain zenoh session with no
UPS code, its publishers set as the face sets its own (reliable, congestion control DROP;
``congestion: block`` in the options makes ``put`` wait instead). ``tcp`` is a UPS node on
TCP/IP, for the gateway's TCP side.

* ``run_pong`` / ``run_ping``: the round-trip roles of ``benchmarks/peers`` (run by
  ``tcp_compare.measure_rtt``; ``service`` is the router, pinned with them).
* ``sink`` / ``source`` / ``gateway``: step roles, driven over a pipe by ``zenoh_face``:
  a source sends ``count`` events at a rate (or flat out) per step, a sink counts each step's
  events (8 bytes: a number, the step), a gateway forwards events that a raw python-can bus
  in its process sends as fast as it can on a ``virtual`` bus.

Every wait here is bounded; the harness kills a role that does not end by its PID.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import importlib.metadata
import json
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable, Coroutine, Iterator
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from ups.benchmarks._procs import process
from ups.benchmarks.peers import PROBE, STOP, Control, Link, seq
from ups.benchmarks.peers._common import probe_until_echoed

if TYPE_CHECKING:
    from ups import Message, Node

PING, PONG, DATA = "bench/zping", "bench/zpong", "bench/zdata"
TAG = struct.Struct("<IH2x")  # an event of a step: its number, the step
PROBE_STEP = 0xFFFF  # a marker event (the gateway's, a step's tail), not counted in any step
TAIL_PAUSE = 0.05  # s between a UPS source's last event of a step and its tail marker
SETUP_TIMEOUT = 20.0
IDLE = 1.0  # a sink's report: this long without an event of the step ends it
REPORT_LIMIT = 30.0  # a sink's report never waits longer than this
TICK = 0.001  # a paced source sends what is due, then sleeps until the next tick
YIELD_EVERY = 256  # a flat-out UPS source lets its loop run this often
IDS = {"pong": 0xBE7D_0001, "ping": 0xBE7D_0002, "sink": 0xBE7D_0003, "source": 0xBE7D_0004,
       "gateway": 0xBE7D_0005, "canpub": 0xBE7D_0006}  # fmt: skip


def _run(main: Coroutine[Any, Any, Any]) -> Any:
    """On uvloop when installed, as ``ups`` runs its daemons."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(main)
    return uvloop.run(main)


def _raw_session(endpoint: str) -> Any:
    """A plain zenoh client session of the router at ``endpoint`` (no scouting)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def _raw_publisher(session: Any, key: str, options: dict[str, Any]) -> Any:
    import zenoh

    block = options.get("congestion") == "block"
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
        reliability=zenoh.Reliability.RELIABLE,
    )


def _raw_matched(pub: Any) -> None:
    """Wait until a subscriber matches ``pub`` (a plain zenoh publisher)."""
    deadline = time.monotonic() + SETUP_TIMEOUT
    while not pub.matching_status.matching:
        if time.monotonic() > deadline:
            raise TimeoutError(f"no subscriber matched within {SETUP_TIMEOUT} s")
        time.sleep(0.005)


def _ups_node(kind: str, endpoint: str, role: str) -> Node:
    from ups import Node

    zenoh, broker = (endpoint, None) if kind == "ups" else (None, endpoint)
    return Node(zenoh=zenoh, broker=broker, name=f"bench-z{role}", node_id=IDS[role],
                join_timeout=SETUP_TIMEOUT)  # fmt: skip


async def _until(predicate: Callable[[], bool], what: str, interval: float = 0.005) -> None:
    deadline = time.monotonic() + (limit := SETUP_TIMEOUT + REPORT_LIMIT)
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} within {limit:.0f} s")
        await asyncio.sleep(interval)


def _matched(node: Node, channel: str) -> Callable[[], bool]:
    """Whether a subscriber elsewhere matches ``channel`` (the Zenoh face knows)."""
    from ups import name_to_uid

    uid, elsewhere = name_to_uid(channel), node.face.subscribed_elsewhere  # type: ignore[attr-defined]
    return lambda: bool(elsewhere(uid))


# --- the round-trip roles (benchmarks/peers interface) -----------------------------------


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
        session = _raw_session(endpoint_of(link))
        try:
            pub = _raw_publisher(session, PONG, link.options)
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
        async with _ups_node("ups", endpoint_of(link), "pong") as node:
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

    _run(main())


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Wait until the pong's subscription matches, probe until an echo comes back, then
    ping-pong; the last ``rounds`` round trips in seconds."""
    if link.options.get("kind") != "ups":
        return _raw_ping(link, warmup, rounds)

    async def main() -> list[float]:
        async with _ups_node("ups", endpoint_of(link), "ping") as node:
            sub = await node.subscribe(PONG)
            await node.advertise(PING)
            await _until(_matched(node, PING), "no subscriber matched")
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

    result: list[float] = _run(main())
    return result


def _raw_ping(link: Link, warmup: int, rounds: int) -> list[float]:
    session = _raw_session(endpoint_of(link))
    try:
        replies = session.declare_subscriber(PONG)
        pub = _raw_publisher(session, PING, link.options)
        _raw_matched(pub)

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


# --- the step roles ----------------------------------------------------------------------


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


def _pipe_recv(conn: Connection, timeout: float = 600.0) -> Any:
    if not conn.poll(timeout):
        raise TimeoutError(f"no command within {timeout} s")
    return conn.recv()


def sink(cfg: dict[str, Any], conn: Connection) -> None:
    """Count DATA events per step; ``("report", step, count)`` answers with the counts (and
    the node's counters: what it counted lost)."""
    tally = Tally()
    if cfg["kind"] == "raw":
        session = _raw_session(cfg["endpoint"])
        try:
            add = tally.add
            key = cfg.get("key") or DATA
            session.declare_subscriber(key, lambda sample: add(sample.payload.to_bytes()))
            conn.send(("ready", None))
            while (cmd := _pipe_recv(conn))[0] == "report":
                done = functools.partial(tally.done, cmd[1], cmd[2], time.perf_counter())
                while not done():
                    time.sleep(0.01)
                conn.send(("result", {**tally.result(cmd[1]), "stats": {}}))
        finally:
            session.close()
        return

    async def main() -> None:
        async with _ups_node(cfg["kind"], cfg["endpoint"], "sink") as node:
            add = tally.add
            await node.subscribe(DATA, callback=lambda m: add(m.data))
            conn.send(("ready", None))
            while (cmd := await asyncio.to_thread(_pipe_recv, conn))[0] == "report":
                done = functools.partial(tally.done, cmd[1], cmd[2], time.perf_counter())
                await _until(done, "no report", 0.01)
                conn.send(("result", {**tally.result(cmd[1]), "stats": node.stats()}))

    _run(main())


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
        session = _raw_session(cfg["endpoint"])
        try:
            pub = _raw_publisher(session, cfg.get("key") or DATA, cfg)
            _raw_matched(pub)
            conn.send(("ready", None))
            while (cmd := _pipe_recv(conn))[0] == "run":
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
        async with _ups_node(cfg["kind"], cfg["endpoint"], "source") as node:
            await node.advertise(DATA)
            await _until(_matched(node, DATA), "no subscriber matched")
            conn.send(("ready", None))
            publish = node.publish_nowait
            while (cmd := await asyncio.to_thread(_pipe_recv, conn))[0] == "run":
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

    _run(main())


# --- the gateway ---------------------------------------------------------------------------


def _blaster(bus: Any, can_id: int) -> Callable[[int, int], dict[str, float]]:
    """``blast(step, count)``: ``count`` frames of ``step`` onto the bus as fast as python-can
    sends them, before the gateway reads any: this thread keeps the interpreter meanwhile
    (``sys.setswitchinterval``), so the gateway then drains a full receive queue, alone."""
    import can

    def blast(step: int, count: int) -> dict[str, float]:
        frames = [can.Message(arbitration_id=can_id, data=TAG.pack(i, step), is_extended_id=True)
                  for i in range(count)]  # fmt: skip
        send, interval = bus.send, sys.getswitchinterval()
        sys.setswitchinterval(min(10.0, 1.0 + count * 20e-6))
        time.sleep(0.05)  # threads already waiting for the interpreter: theirs is the old one
        t0 = time.perf_counter()
        try:
            for frame in frames:
                send(frame)
        finally:
            sys.setswitchinterval(interval)
        end = time.perf_counter()
        return {"sent": count, "seconds": end - t0, "end": end, "cpu_s": time.process_time()}

    return blast


def gateway(cfg: dict[str, Any], conn: Connection) -> None:
    """A ``Gateway`` (``ip``: ``zenoh`` or ``tcp``) on a virtual bus in this process, or the
    floor (``bridge``: a thread that reads the bus and puts each frame's data on the channel's
    key, plain zenoh). A raw python-can bus on the same virtual channel blasts the frames."""
    import can

    from ups import _canproto as p
    from ups import name_to_uid

    raw = can.Bus(interface="virtual", channel=cfg["bus"])
    try:
        if cfg["ip"] == "bridge":
            _bridge(cfg, conn, raw, name_to_uid(DATA), p.make_id(0x80, 0x05, p.FIRST_ETAG))
        else:
            _run(_gateway(cfg, conn, raw))
    finally:
        raw.shutdown()


def _serve_blasts(conn: Connection, raw: Any, can_id: int, stats: Callable[[], Any]) -> None:
    """Answer ``("blast", step, count)`` and ``("stats",)`` (with this process's CPU time) until
    ``("quit",)``."""
    conn.send(("ready", None))
    blast = _blaster(raw, can_id)
    while (cmd := _pipe_recv(conn))[0] != "quit":
        if cmd[0] == "blast":
            conn.send(("done", blast(cmd[1], cmd[2])))
        else:
            conn.send(("stats", {**stats(), "cpu_s": time.process_time()}))


def _bridge(cfg: dict[str, Any], conn: Connection, raw: Any, uid: int, can_id: int) -> None:
    import can

    bus = can.Bus(interface="virtual", channel=cfg["bus"])
    session = _raw_session(cfg["endpoint"])
    stop, forwarded = threading.Event(), [0]
    try:
        pub = _raw_publisher(session, f"ups/{uid:016x}", cfg)

        def forward() -> None:
            recv, put = bus.recv, pub.put
            while not stop.is_set():
                frame = recv(0.05)
                if frame is not None:
                    put(bytes(frame.data))
                    forwarded[0] += 1

        thread = threading.Thread(target=forward, name="bench-bridge", daemon=True)
        thread.start()
        _serve_blasts(conn, raw, can_id, lambda: {"to_zenoh": forwarded[0]})
        stop.set()
        thread.join(1.0)
    finally:
        session.close()
        bus.shutdown()


async def _gateway(cfg: dict[str, Any], conn: Connection, raw: Any) -> None:
    from ups import Node
    from ups._canlink import CanLink
    from ups.gateway import Gateway

    link = CanLink.open(f"virtual:{cfg['bus']}")
    zenoh, broker = (cfg["endpoint"], None) if cfg["ip"] == "zenoh" else (None, cfg["endpoint"])
    gw = Gateway(link, broker, zenoh=zenoh, db=cfg["db"], node_id=IDS["gateway"],
                 bitrate=1_000_000, name="bench-zgateway", join_timeout=SETUP_TIMEOUT)  # fmt: skip
    async with gw:
        side = gw.side
        async with Node(can=link, node_id=IDS["canpub"], name="bench-zcanpub") as pub:
            marker = TAG.pack(0, PROBE_STEP)
            await pub.publish(DATA, marker)  # binds; the gateway forwards once it matches
            await _until(lambda: gw.stats()[f"forwarding_to_{side}"] >= 1, "no forwarding")
            deadline = time.monotonic() + SETUP_TIMEOUT
            while True:  # the publisher's CAN id, as any node on the bus sees it
                frame = await asyncio.to_thread(raw.recv, 0.1)
                if frame is not None and bytes(frame.data) == marker:
                    can_id = frame.arbitration_id
                    break
                if time.monotonic() > deadline:
                    raise TimeoutError("the publisher's event never reached the bus")
        # the publisher node is gone from this process; its binding stays: from here on the
        # raw bus sends its frames, as a node elsewhere on the bus would (from another thread)
        await asyncio.to_thread(_serve_blasts, conn, raw, can_id, gw.stats)
