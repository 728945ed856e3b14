"""Shared fixtures: unique virtual buses, a CAN-ECB per test, and a check for leaked threads."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import signal
import threading
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from ups import Node
from ups import _canproto as p
from ups._canlink import CanLink, open_bus
from ups.broker.can_ecb import CanEcb

from .procs import private_multicast_bus, vcan_bus

_bus_numbers = itertools.count()


def pytest_configure(config: pytest.Config) -> None:
    """With ``UPS_EXPECT_COMPILED=1`` (tests/test_compiled.py), refuse to run on pure Python.

    A suite started in the background of a shell without job control (``scripts/test &``,
    ``nohup``) inherits SIGINT ignored, and so would every process the tests start: Ctrl-C
    (tests/test_ctrl_c.py) would not reach ``ups jaus-ocu``, which relies on Python's own
    handler. The tests start their processes as a terminal would: with SIGINT at its default."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # children get SIG_DFL
    if os.environ.get("UPS_EXPECT_COMPILED") == "1":
        import ups._tcplink

        if not (ups._tcplink.__file__ or "").endswith(".so"):
            raise pytest.UsageError(f"expected the compiled UPS, got {ups._tcplink.__file__}")


#: the test files that take longest (worker-seconds, 3 workers on 2 cores: 95 to 23 s), run
#: first: xdist's loadfile hands the files out in the order collected, and a long one started
#: last would keep one worker busy while the others wait (scripts/test)
SLOWEST_FIRST = (
    "tests/test_compiled.py", "tests/test_cecb_m0.py", "tests/conformance/test_second_ecb.py",
    "tests/test_cnode_build.py", "tests/conformance/test_unheld_requests.py",
    "tests/test_start_orders.py", "tests/test_demo_jaus.py",
    "tests/test_forged_serving_processes.py", "tests/test_can_ecb_processes.py",
    "tests/test_can_fuzz.py", "tests/test_can_trust.py", "tests/test_tcp_processes.py",
)  # fmt: skip


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))  # stable
    if os.environ.get("UPS_EXPECT_COMPILED") == "1":
        skip = pytest.mark.skip(reason="patches internals: pure Python only")
        for item in items:
            if item.get_closest_marker("pure"):
                item.add_marker(skip)


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if os.environ.get("UPS_EXPECT_COMPILED") == "1":
        import ups._tcplink

        terminalreporter.write_line(f"ups: compiled build ({ups._tcplink.__file__})")


@pytest.fixture
def bus(request: pytest.FixtureRequest) -> str:
    """A python-can virtual bus of this test's own, so tests cannot hear each other."""
    return f"virtual:{request.node.name}-{os.getpid()}-{next(_bus_numbers)}"


@pytest.fixture
def raw_bus(bus: str) -> Iterator[can.BusABC]:
    """A plain python-can bus on the test's bus: to inject frames or watch the wire."""
    raw = can.Bus(interface="virtual", channel=bus.partition(":")[2])
    yield raw
    raw.shutdown()


def send_management(raw: can.BusABC | CanLink, msg: p.Management) -> None:
    """Put one management frame on the bus, as a forger (or a node of another program) would."""
    can_id, data = p.encode(msg)
    if isinstance(raw, CanLink):
        raw.send(can_id, data)
    else:
        raw.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))


async def handled(node: Node, raw: can.BusABC) -> None:
    """Wait until ``node`` has handled every frame sent on ``raw`` so far (and every frame any
    sender put on the bus before this call): a malformed frame goes after them (a Hello with
    7 bytes), which the node counts (a virtual bus keeps each receiver's frames in order)."""
    counted = node.stats()["malformed"]
    hello, _ = p.encode(p.Hello(0))
    raw.send(can.Message(arbitration_id=hello, data=bytes(7), is_extended_id=True))
    await eventually(lambda: node.stats()["malformed"] > counted)


@contextlib.asynccontextmanager
async def joined_nodes(bus: str, ids: list[int]) -> AsyncIterator[list[Node]]:
    """CAN nodes with these ids, joined together (each given 15 s), closed on exit."""
    async with contextlib.AsyncExitStack() as stack:
        started = [Node(can=bus, node_id=i, join_timeout=15) for i in ids]
        for node in started:
            stack.push_async_callback(node.close)
        await asyncio.gather(*(n.start() for n in started))
        yield started


@contextlib.asynccontextmanager
async def running_ecb(bus: str, db: Path, **options: Any) -> AsyncIterator[CanEcb]:
    """A started CAN-ECB on its own link to ``bus``; closed (again, if need be) on exit."""
    link = CanLink.open(bus)
    broker = CanEcb(link, db, **options)
    try:
        await broker.start()
        yield broker
    finally:
        broker.close()
        link.close()


@pytest.fixture
async def ecb(bus: str, tmp_path: Path) -> AsyncIterator[CanEcb]:
    """A CAN-ECB serving the test's bus, its tables in a fresh SQLite file (a short recovery
    window: nodes join after it)."""
    async with running_ecb(bus, tmp_path / "ecb.db", recovery=0.1) as broker:
        yield broker


@pytest.fixture(autouse=True)
def _no_leaked_threads() -> Iterator[None]:
    before = {t.ident for t in threading.enumerate()}
    yield
    leaked = [
        t.name
        for t in threading.enumerate()
        if t.ident not in before and t.name.startswith("ups-") and t.is_alive()
    ]
    assert not leaked, f"threads left running: {leaked}"


async def eventually(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    """Wait until ``predicate()`` holds (checked every loop tick), or fail after ``timeout``."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not predicate():
        if loop.time() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        await asyncio.sleep(0.001)


class HeldBus(can.BusABC):
    """A virtual bus whose receiving can be held, as a busy node's: frames wait, in order."""

    def __init__(self, channel: str) -> None:
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.reading = threading.Event()
        self.reading.set()
        self.parked = threading.Event()  # the reader waits for ``reading``, in no receive call
        super().__init__(channel=channel)
        self.channel_info = f"held virtual {channel}"

    async def hold(self) -> None:
        """Stop receiving: once this returns, frames wait until ``reading`` is set again (a
        receive call under way when it was asked may still take frames sent before)."""
        self.reading.clear()
        self.parked.clear()
        if not await asyncio.to_thread(self.parked.wait, 5.0):
            raise AssertionError("the bus's reader never stopped")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self.reading.is_set():
            self.parked.set()
            if not self.reading.wait(timeout):
                return None, False
        return self.inner.recv(timeout), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


@pytest.fixture(
    params=[
        pytest.param("udp_multicast", marks=pytest.mark.netns),
        pytest.param("socketcan", marks=pytest.mark.socketcan),
    ]
)
def mbus(request: pytest.FixtureRequest) -> str:
    """A bus that separate processes share: udp_multicast in a private network namespace, and
    (a second run of the test) SocketCAN vcan0 inside User-Mode Linux."""
    return private_multicast_bus() if request.param == "udp_multicast" else vcan_bus()


@pytest.fixture
def wire(mbus: str) -> Iterator[can.BusABC]:
    """A listener on ``mbus``, opened before any process so that it hears every frame."""
    listener = open_bus(mbus)
    yield listener
    listener.shutdown()


#: Zenoh's waits (microseconds) for room in a link's queue before it drops an event put with
#: congestion control "drop", made long enough that only a link that is really full drops.
#: Zenoh's defaults (1 ms; 50 ms for a fragmented event) are shorter than its sending thread may
#: wait for a core on a busy machine. For the test's router, and a node's ``zenoh_config``:
#: ``{"transport": {"link": {"tx": {"queue": {"congestion_control": {"drop": PATIENT_DROP}}}}}}``.
PATIENT_DROP = {"wait_before_drop": 5_000_000, "max_wait_before_drop_fragments": 5_000_000}


@pytest.fixture(scope="module")
def zenoh_router() -> Iterator[str]:
    """A Zenoh router (Zenoh's own, as ``ups zenoh-router`` runs it) on loopback; its
    endpoint. Multicast scouting off: nothing leaves loopback.

    One setting differs: it waits up to :data:`PATIENT_DROP` for room in its queue to a
    subscriber before it drops an event (Zenoh's defaults: 1 ms, 50 ms for the fragments of a
    large one). Nodes put with congestion control "drop"; on a busy machine Zenoh's sending
    thread can wait longer than that for a core, and an event on an idle link was lost.
    """
    import json
    import socket

    import zenoh

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    for key, value in PATIENT_DROP.items():
        conf.insert_json5(f"transport/link/tx/queue/congestion_control/drop/{key}", str(value))
    session = zenoh.open(conf)
    yield endpoint
    session.close()  # type: ignore[no-untyped-call]
