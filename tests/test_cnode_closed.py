"""libups ported exactly as ``c/README.md`` says, on a CAN controller that starts closed.

Many controllers receive nothing until their acceptance filters are programmed: bxCAN with no
filter bank active, Zephyr's CAN API without an RX filter, a SocketCAN socket with an empty
filter list (``c/examples/socketcan.c`` opens one so; ``tests/socketcan`` runs the examples).
``ClosedController`` lets through to the receive ring only the frames of a python-can bus that
its filter banks accept, and has none active at reset. On it run ``GuidePort``, the README's
``app_init``/``app_loop`` step for step over ``ups._cnode``, and the README's example itself,
compiled as it is written with a harness for the board's functions: both program the banks only
on ``UPS_NOTE_FILTERS``, read after ``ups_start`` and after every ``ups_rx`` and ``ups_tick``. On
the bus with them: the real CAN-ECB and a Python node.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import io
import subprocess
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import pytest

from ups import Node, name_to_uid
from ups import _canproto as p
from ups._cnode import (
    FRAME_EXT,
    FRAME_FD,
    NOTE_FILTERS,
    READY,
    CNode,
    Event,
    now_ms,
    to_message,
)
from upscli import main

from .cnode_helpers import CanEcb, Wire
from .conftest import eventually
from .test_cnode_build import C_SOURCES

SPEED, CMD, OTHER = (name_to_uid(n) for n in ("robot/speed", "robot/cmd", "robot/other"))
MGMT = (0x7F << 14, 0x7F << 14)  # the CAN-ECB's frames: TxNode 0x7F


@dataclass
class ClosedController:
    """The acceptance filtering of a CAN controller in front of a python-can bus: ``banks``
    filter banks of (id, mask) over the 29-bit identifier, none active at reset, so it receives
    nothing until the port programs them. ``poll`` is its receive interrupt: the frames it
    accepts go into ``ring``; the others are dropped (kept in ``rejected`` for the test)."""

    bus: can.BusABC
    banks: int
    active: list[tuple[int, int]] = field(default_factory=list)
    programmed: int = 0
    ring: deque[can.Message] = field(default_factory=deque)
    rejected: list[can.Message] = field(default_factory=list)

    def program(self, filters: list[tuple[int, int]]) -> None:
        """The guide's ``program_filters``: with more filters than banks, one bank accepts every
        extended frame (the library filters in software)."""
        self.programmed += 1
        self.active = filters if len(filters) <= self.banks else [(0, 0)]

    def poll(self) -> None:
        while (msg := self.bus.recv(timeout=0)) is not None:
            ident = msg.arbitration_id
            if msg.is_extended_id and any(ident & m == i & m for i, m in self.active):
                self.ring.append(msg)
            else:
                self.rejected.append(msg)


@dataclass
class GuidePort:
    """``app_init`` and ``app_loop`` of ``c/README.md`` over a ``ClosedController``."""

    node: CNode
    controller: ClosedController
    events: list[Event] = field(default_factory=list)

    def take_notes(self) -> None:
        if self.node.notes() & NOTE_FILTERS:
            self.controller.program(self.node.filters())

    def init(self) -> None:
        self.node.start(now_ms())
        self.take_notes()  # the filters, before the Knock goes

    def loop(self) -> None:
        now = now_ms()
        self.controller.poll()
        while self.controller.ring:
            event = self.node.rx(self.controller.ring.popleft(), now)
            if event is not None:
                self.events.append(event)
            self.take_notes()  # before the next frame
        self.node.tick(now)
        self.take_notes()
        for can_id, flags, data in self.node.tx():
            self.controller.bus.send(to_message(can_id, flags, data))


@contextlib.asynccontextmanager
async def guide_port(bus: str, node_id: int, banks: int) -> AsyncIterator[GuidePort]:
    """A started ``GuidePort`` of the minimal build on ``bus``, its loop run every millisecond."""
    raw = can.Bus(interface="virtual", channel=bus.partition(":")[2])
    port = GuidePort(CNode(node_id, variant="min"), ClosedController(raw, banks))

    async def run() -> None:
        while True:
            port.loop()
            await asyncio.sleep(0.001)

    port.init()
    task = asyncio.get_running_loop().create_task(run())
    try:
        yield port
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        raw.shutdown()


@pytest.mark.parametrize("banks", [14, 1], ids=["bxcan-14-banks", "fewer-banks-than-filters"])
async def test_the_guides_port_joins_and_binds_through_a_controller_that_starts_closed(
    bus: str, ecb: CanEcb, banks: int
) -> None:
    async with guide_port(bus, 0xC105ED, banks) as port, Node(can=bus, node_id=0x5C) as py:
        node = port.node
        speed = node.subscribe(SPEED, now_ms())
        cmd = node.advertise(CMD, 8, now_ms())
        await eventually(lambda: node.txnode is not None, 10)
        assert ecb.txnodes[0xC105ED] == node.txnode
        await eventually(lambda: node.channel_state(speed) == READY, 10)  # UPS_CHANNEL_BOUND
        await eventually(lambda: node.channel_state(cmd) == READY, 10)
        etag = node.channel_etag(speed)
        expected = [MGMT, (etag, 0x3FFF)] if banks > 1 else [(0, 0)]
        assert port.controller.active == expected
        await py.publish("robot/speed", b"\x01\x02")
        await eventually(lambda: [e.data for e in port.events] == [b"\x01\x02"])
        sub = await py.subscribe("robot/cmd")
        assert node.publish(cmd, b"\xc0\xde") == 0
        assert (await sub.get_msg(timeout=5)).data == b"\xc0\xde"
        if banks > 1:  # the banks filter: an event the node did not subscribe to never reaches it
            await py.advertise("robot/other")
            await py.publish("robot/other", b"no")
            other = ecb.etags[OTHER]
            await eventually(
                lambda: any(m.arbitration_id & 0x3FFF == other for m in port.controller.rejected)
            )
            assert node.counters()["filtered"] == node.counters()["unknown"] == 0


# --- the README's example, compiled as it is written -------------------------------------------

HARNESS_H = """#include <stdint.h>
#include "ups.h"
/* what the README's example leaves to the board, here the test's (a Python controller) */
uint64_t node_id(void);
uint32_t millis(void);
int rx_ring_pop(ups_frame_t *frame);
void program_filters(ups_filter_t *filters, int count);
int tx_mailbox_free(void);
void tx_mailbox_write(const ups_frame_t *frame);
void apply_brake(const uint8_t *data, uint16_t size);
int reading_due(uint32_t now);
extern uint8_t reading[8];
void app_init(void);
void app_loop(void);
void harness_set(uint64_t id, int (*rx)(ups_frame_t *), void (*program)(ups_filter_t *, int),
                 void (*tx)(const ups_frame_t *), void (*brake)(const uint8_t *, uint16_t));
void harness_clock(uint32_t now, int due);
"""

HARNESS_C = """#include "harness.h"
static uint64_t id_;
static uint32_t now_;
static int due_;
static int (*rx_)(ups_frame_t *);
static void (*program_)(ups_filter_t *, int);
static void (*tx_)(const ups_frame_t *);
static void (*brake_)(const uint8_t *, uint16_t);
uint8_t reading[8] = {0x01, 0x2c};
void harness_set(uint64_t id, int (*rx)(ups_frame_t *), void (*program)(ups_filter_t *, int),
                 void (*tx)(const ups_frame_t *), void (*brake)(const uint8_t *, uint16_t))
{ id_ = id; rx_ = rx; program_ = program; tx_ = tx; brake_ = brake; }
void harness_clock(uint32_t now, int due) { now_ = now; due_ |= due; }
uint64_t node_id(void) { return id_; }
uint32_t millis(void) { return now_; }
int rx_ring_pop(ups_frame_t *frame) { return rx_(frame); }
void program_filters(ups_filter_t *filters, int count) { program_(filters, count); }
int tx_mailbox_free(void) { return 1; }
void tx_mailbox_write(const ups_frame_t *frame) { tx_(frame); }
void apply_brake(const uint8_t *data, uint16_t size) { brake_(data, size); }
int reading_due(uint32_t now) { int due = due_; (void)now; due_ = 0; return due; }
"""

MIN = ["-DUPS_CHANNELS=8", "-DUPS_TX_DEPTH=4", "-DUPS_DECLARATIONS=0", "-DUPS_COUNTER_T=uint16_t"]


class Frame8(ctypes.Structure):
    """``ups_frame_t`` of a build without CAN FD."""

    _fields_ = [("id", ctypes.c_uint32), ("flags", ctypes.c_uint8), ("len", ctypes.c_uint8),
                ("data", ctypes.c_uint8 * 8)]  # fmt: skip


class Filter(ctypes.Structure):
    _fields_ = [("id", ctypes.c_uint32), ("mask", ctypes.c_uint32)]


RX = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(Frame8))
PROGRAM = ctypes.CFUNCTYPE(None, ctypes.POINTER(Filter), ctypes.c_int)
TX = ctypes.CFUNCTYPE(None, ctypes.POINTER(Frame8))
BRAKE = ctypes.CFUNCTYPE(None, ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint16)


def readme_example() -> str:
    """The C code block of c/README.md's *Using it*."""
    readme = (Path(__file__).resolve().parent.parent / "c" / "README.md").read_text()
    start = readme.index("```c\n", readme.index("## Using it")) + 5
    return readme[start : readme.index("\n```\n", start)] + "\n"


def build_readme_example(tmp_path: Path) -> ctypes.CDLL:
    """The README's example, the library (minimal build) and the harness as one shared object;
    robots.h made as the README says (``ups catalog --c-header robots.toml -o robots.h``)."""
    root = Path(__file__).resolve().parent.parent
    with contextlib.redirect_stdout(io.StringIO()):
        catalog = root / "examples" / "robots.toml"
        assert main(["catalog", "--c-header", str(catalog), "-o", str(tmp_path / "robots.h")]) == 0
    (tmp_path / "harness.h").write_text(HARNESS_H)
    (tmp_path / "harness.c").write_text(HARNESS_C)
    (tmp_path / "example.c").write_text(readme_example())
    sources = ["example.c", "harness.c", *(str(root / "c" / s) for s in C_SOURCES)]
    subprocess.run(
        ["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O1", "-fPIC", "-shared",
         *MIN, f"-I{root / 'c'}", f"-I{tmp_path}", "-include", "harness.h", "-o", "example.so",
         *sources],
        cwd=tmp_path, check=True,
    )  # fmt: skip
    lib = ctypes.CDLL(str(tmp_path / "example.so"))
    lib.harness_clock.argtypes = [ctypes.c_uint32, ctypes.c_int]
    lib.harness_set.argtypes = [ctypes.c_uint64, RX, PROGRAM, TX, BRAKE]
    return lib


async def test_the_readmes_example_compiled_as_written_joins_through_a_closed_controller(
    bus: str, ecb: CanEcb, tmp_path: Path
) -> None:
    lib = build_readme_example(tmp_path)
    raw = can.Bus(interface="virtual", channel=bus.partition(":")[2])
    controller = ClosedController(raw, banks=14)
    brakes: list[bytes] = []
    unfiltered: list[int] = []

    def rx(frame: ctypes._Pointer[Frame8]) -> int:
        while controller.ring:
            msg = controller.ring.popleft()
            if len(msg.data) <= 8:  # a longer CAN FD frame: dropped, as the guide says
                f = frame.contents
                f.id = msg.arbitration_id
                f.flags = (FRAME_EXT if msg.is_extended_id else 0) | (FRAME_FD if msg.is_fd else 0)
                f.len = len(msg.data)
                ctypes.memmove(f.data, bytes(msg.data), len(msg.data))
                return 1
        return 0

    def program(filters: ctypes._Pointer[Filter], count: int) -> None:
        controller.program([(filters[i].id, filters[i].mask) for i in range(count)])

    def tx(frame: ctypes._Pointer[Frame8]) -> None:
        f = frame.contents
        if controller.programmed == 0:
            unfiltered.append(f.id)  # sent before the filters were programmed
        raw.send(to_message(f.id, f.flags, bytes(f.data[: f.len])))

    def brake(data: ctypes._Pointer[ctypes.c_uint8], size: int) -> None:
        brakes.append(ctypes.string_at(data, size))

    callbacks = (RX(rx), PROGRAM(program), TX(tx), BRAKE(brake))  # alive while the lib runs
    lib.harness_set(0xE1A3, *callbacks)
    due: list[int] = []  # a reading to publish: handed to reading_due() once

    async def run() -> None:
        while True:
            controller.poll()
            lib.harness_clock(now_ms(), due.pop() if due else 0)
            lib.app_loop()
            await asyncio.sleep(0.001)

    lib.harness_clock(now_ms(), 0)
    lib.app_init()
    task = asyncio.get_running_loop().create_task(run())
    try:
        async with Node(can=bus, node_id=0x5D) as py:
            await eventually(lambda: 0xE1A3 in ecb.txnodes, 10)  # joined
            assert unfiltered == [] and controller.programmed >= 1
            brake_uid = name_to_uid("robot/brake")
            await eventually(lambda: brake_uid in ecb.etags, 10)
            await eventually(lambda: (ecb.etags[brake_uid], 0x3FFF) in controller.active, 10)
            await py.publish("robot/brake", b"\x01")
            await eventually(lambda: brakes == [b"\x01"])
            sub = await py.subscribe("robot/speed")
            due.append(1)  # app_loop publishes it once robot/speed is bound
            assert (await sub.get_msg(timeout=10)).data == b"\x01\x2c"
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        raw.shutdown()


def test_ups_start_raises_the_first_filters_note() -> None:
    w = Wire(variant="min")
    assert w.node.notes() == 0  # ups_init: the node does nothing yet
    w.node.start(w.now)
    assert w.node.notes() & NOTE_FILTERS
    assert w.node.filters() == [MGMT]
    assert w.sent == []  # the Knock is queued, not sent yet: the filters go first
    w.drain()
    assert w.mgmt() == [p.Knock()]
