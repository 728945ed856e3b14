"""libups as a board runs it: the Cortex-M0+ image of ``make size`` in an emulator (issue 42).

The image is compiled and linked as c/size.py does for a board, loaded into an emulated
Cortex-M0+ (ups/_armnode.py) and driven through libups's API as the host build is: on a real
python-can bus beside our CAN-ECB and a Python node, frame for frame against the host build of
the same configuration, and for the worst-case cycles of c/cycles.json.
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ups import Channel, Node
from ups import _canproto as p
from ups._armnode import ArmNode, Fault, build_image
from ups._canlink import CanLink
from ups._cnode import C_DIR, CNode, CNodeRunner, Event, now_ms
from ups.broker.can_ecb import CanEcb

pytest.importorskip("unicorn")
MARGIN = 1.10  #: a function's scenario may cost this much more than c/cycles.json says


async def _until(check: object, timeout: float = 20.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not check():  # type: ignore[operator]
        assert loop.time() < deadline, "timed out"
        await asyncio.sleep(0.01)


async def test_the_m0_image_joins_and_exchanges_events_with_python_nodes(tmp_path: Path) -> None:
    channel = f"m0-{id(tmp_path)}"
    link = CanLink.open(f"virtual:{channel}")
    ecb = CanEcb(link, tmp_path / "ecb.db", recovery=0.2)
    await ecb.start()
    bus = can.Bus(interface="virtual", channel=channel)
    node = ArmNode(0x00C0_FFEE_0000_0042)
    got: list[Event] = []
    runner = CNodeRunner(bus, [node], lambda _n, ev, _t: got.append(ev))
    runner.start_all()
    task = asyncio.get_running_loop().create_task(runner.run())
    python = Node(can=f"virtual:{channel}", node_id=0x42)
    try:
        await python.start()
        heard = await python.subscribe("m0/out")
        await python.advertise("m0/in")
        out = node.advertise(Channel.named("m0/out").uid, 8, now_ms())
        into = node.subscribe(Channel.named("m0/in").uid, now_ms())
        await _until(lambda: node.channel_state(out) == 2 and node.channel_state(into) == 2)
        assert node.txnode is not None and node.txnode in ecb.txnodes.values()
        for k in range(5):  # the image to Python
            assert node.publish(out, bytes([k, 0xAA])) == 0
            msg = await heard.get_msg(timeout=10)
            assert msg.data == bytes([k, 0xAA])
        for k in range(5):  # Python to the image
            await python.publish("m0/in", bytes([k]))
            await _until(lambda k=k: len(got) > k)
        assert [ev.data for ev in got] == [bytes([k]) for k in range(5)]
        assert node.counters()["malformed"] == 0
    finally:
        task.cancel()
        await python.close()
        bus.shutdown()
        ecb.close()
        link.close()


_FAULTY = r"""
#include <stdint.h>
uint32_t ups_test_load_word(const uint8_t *p);
void ups_test_store(uint32_t address);
uint32_t ups_test_load_word(const uint8_t *p)
{
    return *(const volatile uint32_t *)(const void *)p;
}
void ups_test_store(uint32_t address) { *(volatile uint32_t *)address = 1u; }
"""


def test_what_faults_on_the_board_stops_the_run_with_its_address(tmp_path: Path) -> None:
    source = tmp_path / "faulty.c"
    source.write_text(_FAULTY)
    node = ArmNode(1, elf=build_image("minimal", (source,)))
    mcu = node.mcu
    buf = mcu.alloc(8, 8)
    mcu.write(buf, bytes(range(8)))
    assert mcu.call("ups_test_load_word", buf + 4) == 0x07060504  # aligned: as the board
    with pytest.raises(Fault) as caught:
        mcu.call("ups_test_load_word", buf + 1)  # the host build reads it; an M0+ faults
    assert caught.value.address == buf + 1 and "unaligned 4-byte read" in str(caught.value)
    assert caught.value.pc == mcu.symbols["ups_test_load_word"] & ~1
    with pytest.raises(Fault, match="outside flash and RAM") as caught:
        mcu.call("ups_test_store", 0x4000_0000)
    assert caught.value.address == 0x4000_0000
    with pytest.raises(Fault, match="a write to flash"):
        mcu.call("ups_test_store", mcu.symbols["ups_init"] & ~3)
    node.start(0)  # the node itself is unharmed by a call that faulted
    assert node.join_state == 1


ECB = 0x7F
_ME = 0x0123_4567_89AB_CDEF
_UIDS = (0x5000_0000_0000_0000, 0x5000_0000_0000_0001)
_valid = [(*p.encode(m), 1) for m in (  # the frames that take the node somewhere
    p.Census(0), p.Query(1, (0, 1, 2)), p.Offer(5, _ME), p.Assign(5, _ME), p.Assign(6, _ME),
    p.Bind(0x10, _UIDS[0]), p.Bind(0x11, _UIDS[1]), p.Bind(0x10, _UIDS[1]), p.Hello(7),
    p.EtagsFull(_UIDS[0]), p.Limit(5, _UIDS[1]), p.TxNodesFull(_ME), p.Serving(3),
)]  # fmt: skip
_frames = st.one_of(st.sampled_from(_valid), st.tuples(
    st.builds(lambda pr, tx, e: (pr << 21) | (tx << 14) | e, st.sampled_from([0, 1, 0x80, 0x20]),
              st.sampled_from([ECB, 0, 5, 0x21]), st.integers(0, 0x3FFF)),
    st.binary(max_size=8),
    st.sampled_from([1, 1, 1, 0, 1 | 8]),
))  # fmt: skip


@settings(max_examples=80, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.lists(st.one_of(_frames, st.integers(1, 700)), max_size=40), st.integers(0, 2**32 - 1))
def test_the_m0_image_does_what_the_host_build_does(steps: list[object], start: int) -> None:
    """Frame for frame and tick for tick, the Cortex-M0+ image and the host build of the same
    configuration (minimal) send the same frames, deliver the same events and count alike."""
    host, arm = CNode(_ME, variant="min"), _arm()
    now = start
    for node in (host, arm):
        node.start(now)
        node.subscribe(_UIDS[0], now)
        node.advertise(_UIDS[1], 8, now)
    for step in steps:
        if isinstance(step, int):
            now = (now + step) & 0xFFFF_FFFF
            outs = [(n.tick(now), list(n.tx()), n.notes()) for n in (host, arm)]
        else:
            can_id, data, flags = step  # type: ignore[misc]
            outs = [(n.rx_raw(can_id, data, flags, now), list(n.tx()), n.notes())
                    for n in (host, arm)]  # fmt: skip
        assert outs[0] == outs[1], step
    assert host.counters() == arm.counters()
    assert host.join_state == arm.join_state and host.txnode == arm.txnode
    assert host.filters() == arm.filters()


_arm_node: list[ArmNode] = []


def _arm() -> ArmNode:
    """A fresh node on one emulator (loading the image once): ups_init sets the whole state."""
    if not _arm_node:
        _arm_node.append(ArmNode(_ME))
    node = _arm_node[0]
    node._check(node._call("ups_init", node._at_node, node.node_id, 0, wide=(1,)), "init")
    return node


def test_no_function_costs_more_than_the_cycles_table_says() -> None:
    """The deterministic workload of c/cycles.py, again, and the inputs its searches found
    dearest (cycles.json's "recorded", no new search): each public function's worst case within
    MARGIN of the figure c/cycles.json (and c/README.md's table) gives."""
    sys.path.insert(0, str(C_DIR))
    try:
        import cycles
    finally:
        sys.path.remove(str(C_DIR))
    data = json.loads((C_DIR / "cycles.json").read_text())
    for config, entries in data["recorded"].items():
        bound = cycles.Bound(config)
        now = {n: bound.play(s)[n].cycles for n, s in cycles.recorded_steps(entries).items()}
        # the table is never below what a recorded input cost when it was written
        assert all(data["worst"][config][n]["cycles"] >= e["cycles"] for n, e in entries.items())
        grown = {n: (entries[n]["cycles"], c) for n, c in now.items()
                 if c > entries[n]["cycles"] * MARGIN}  # fmt: skip
        assert not grown, f"{config}: recorded inputs cost more (run make -C c cycles): {grown}"
    table = data["scenario"]
    for config in ("minimal", "full"):
        now = {n: c.cycles for n, c in cycles.scenario(config).items()}
        assert set(now) == set(table[config]), f"{config}: functions measured changed"
        grown = {n: (table[config][n]["cycles"], c) for n, c in now.items()
                 if c > table[config][n]["cycles"] * MARGIN}  # fmt: skip
        assert not grown, (
            f"{config}: worst cases grew past the table (run make -C c cycles): {grown}"
        )
