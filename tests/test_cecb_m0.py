"""libups-ecb as a board runs it: the CAN-ECB's Cortex-M0+ image (ecb-full) in the emulator, as
``CEcb``'s backend (``ups/_armecb.py``, issue 42), in this process.

Frame for frame and tick for tick, the image and the host build answer alike; a call past the
instruction budget halts the CAN-ECB: it sends nothing more, says why, and its state file keeps
the blob it last wrote.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ups import _canproto as p
from ups._armecb import BUDGET, BUILDS
from ups._armnode import build_image
from ups._canlink import CanLink
from ups._cnode import C_DIR
from ups.broker.c_ecb import Backend, CEcb, Config, backend

from .conformance._frames import SUB_BIND, Bind, Census, Knock, nibbles
from .conformance._wire import RawNode, Wire

pytest.importorskip("unicorn")

_INSTANCE = 0x5EED_0000_C0DE_0042
_IDS = (0x0123_4567_89AB_CDEF, 0x0123_4567_89AB_CDE0, 0xF000_0000_0000_0001)
_UIDS = (0x5000_0000_0000_0000, 0x5000_0000_0000_0001, 0x7777)


def _f(*messages: p.Management) -> list[tuple[int, bytes, int]]:
    return [(*p.encode(m), 1) for m in messages]


#: a bus to start from: TxNode 5 claimed in the recovery window (adopted), then a node joins
#: (Knock, the Census, its answer, the Offer, its claim: TxNode 0)
_PROLOGUE = [_f(p.Request(p.CLAIM, 5, _IDS[2])), 150, _f(p.Knock()), 10,
             _f(*(p.Stage(0, k, n) for k, n in enumerate(nibbles(_IDS[0])))), 100,
             _f(p.Request(p.CLAIM, 0, _IDS[0]))]  # fmt: skip
_valid = [(*p.encode(m), 1) for m in (  # what takes the CAN-ECB somewhere
    p.Knock(), *(p.Stage(e, s, n) for e in (0, 1) for s in (0, 15) for n in (0, 0xF)),
    *(p.Request(p.CLAIM, t, i) for t in (0, 1, 5) for i in _IDS),
    *(p.Request(k, t, u) for k in (p.SUB_BIND, p.PUB_BIND, p.UNSUB) for t in (0, 1, 5)
      for u in _UIDS),
    p.Request(p.PUB_BIND, 5, _UIDS[1], 2), p.Declare(5, 0x10, 8, 100, 50, 0),
    p.Declare(0, 0x11, 8, 20, 20, 3), p.Roster(5, 0), p.Roster(0, 0x5000_0000_0000_0001),
    p.Holds(False, 5, 0x10, _UIDS[0]), p.Holds(True, 1, 0x12, _UIDS[1]),
)]  # fmt: skip
_election = _f(p.Hello(7), p.Serving(3), p.Serving(0xFFFF_FFFF_FFFF_FFFF), p.Probe(9),
               p.Assign(5, _IDS[0]), p.Bind(0x10, _UIDS[2]))  # another CAN-ECB's  # fmt: skip
_frames = st.one_of(st.sampled_from(_valid), st.sampled_from(_valid), st.sampled_from(_valid),
                    st.sampled_from(_election), st.tuples(
    st.builds(lambda pr, tx, e: (pr << 21) | (tx << 14) | e, st.sampled_from([0, 1, 0x20]),
              st.sampled_from([0x7F, 0, 5, 0x21]), st.integers(0, 0x3FFF)),
    st.binary(max_size=8),
    st.sampled_from([1, 1, 1, 0, 1 | 8]),
))  # fmt: skip
_answers = st.builds(  # a joiner's whole answer to a Census of epoch e
    lambda e, i: [(*p.encode(p.Stage(e, k, n)), 1) for k, n in enumerate(nibbles(i))],
    st.integers(0, 3), st.sampled_from(_IDS),
)  # fmt: skip


def _config() -> bytes:
    cfg = Config.from_buffer_copy(backend("host").default_config())
    cfg.recovery_ms, cfg.max_channels = 100, 64  # the image's table is smaller than the host's
    return bytes(cfg)


_arm: list[Backend] = []


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.lists(st.one_of(_frames, _answers, st.integers(1, 300)), max_size=50),
       st.integers(0, 2**32 - 1))  # fmt: skip
def test_the_m0_image_does_what_the_host_build_does(steps: list[object], start: int) -> None:
    """The same frames sent, notes raised, counters, roles, tables and blob."""
    if not _arm:
        _arm.append(backend("m0"))  # one emulator (ups_ecb_init sets the whole state)
    host, arm = backend("host"), _arm[0]
    for ecb in (host, arm):
        assert ecb.init(_config(), _INSTANCE) == 0
        ecb.start(start)
    now = start

    def out(ecb: Backend) -> tuple[int, list[tuple[int, int, bytes]]]:
        notes = ecb.notes()
        return notes, list(iter(ecb.pop_tx, None))

    assert out(host) == out(arm)
    for step in [*_PROLOGUE, *steps]:
        if isinstance(step, int):
            now = (now + step) & 0xFFFF_FFFF
            for ecb in (host, arm):
                ecb.tick(now)
        else:
            for can_id, data, flags in step if isinstance(step, list) else [step]:  # type: ignore[misc]
                for ecb in (host, arm):
                    ecb.rx(now, can_id, flags, data)
        assert out(host) == out(arm), step
    assert host.counters() == arm.counters()
    assert host.role() == arm.role()
    for table, size in (("node", 127), ("channel", 64)):  # the entries in use
        used = [[e for e in map(getattr(b, table), range(size)) if e[0] >= 0] for b in (host, arm)]
        assert used[0] == used[1], table
    assert host.save() == arm.save()


async def test_a_call_past_the_budget_halts_it_and_the_state_file_keeps_the_last_blob(
    tmp_path: Path,
) -> None:
    """The image's ups_ecb_rx runs past its budget (lowered here, as if it ran for ever): the
    CAN-ECB says so, answers nothing more, and close writes no blob."""
    channel = f"cecb-m0-budget-{id(tmp_path)}"
    state = tmp_path / "ecb.state"
    wire = Wire(channel)
    link = CanLink.open(f"virtual:{channel}")
    ecb = CEcb(link, state, recovery=0.2, target="m0")
    halted = asyncio.Event()
    ecb.on_halt = halted.set
    try:
        await ecb.start()
        node = RawNode(wire, _IDS[0])
        await node.join()
        await node.ask(SUB_BIND, _UIDS[0])
        assert ecb.healthy and ecb.halted is None
        written = state.read_bytes()
        ecb._c.budget = 50  # type: ignore[attr-defined]  # the backend's, for this test
        since = wire.send(node.request(SUB_BIND, _UIDS[1]))
        await asyncio.wait_for(halted.wait(), 10)
        assert ecb.halted is not None and "ran past 50 instructions" in ecb.halted
        ecb._c.budget = BUDGET  # type: ignore[attr-defined]  # its tables are still readable
        assert not ecb.healthy and ecb.stats()["healthy"] is False
        wire.send(Knock())
        await wire.expect_none((Bind, Census), since=since, window=0.5, what="a halted CAN-ECB")
    finally:
        ecb.close()
        link.close()
        await wire.close()
    assert state.read_bytes() == written  # close wrote nothing after the halt


async def test_the_small_bus_image_serves_a_node(tmp_path: Path) -> None:
    """``--build small``: the ecb-small image (16 nodes, 64 channels, 16-bit counters)."""
    channel = f"cecb-m0-small-{id(tmp_path)}"
    wire = Wire(channel)
    link = CanLink.open(f"virtual:{channel}")
    ecb = CEcb(link, tmp_path / "ecb.state", recovery=0.2, target="m0", variant="small")
    try:
        await ecb.start()
        assert ecb.config["nodes"] == 16 and ecb.config["channels"] == 64
        node = RawNode(wire, _IDS[1])
        txnode = await node.join()
        bind = await node.ask(SUB_BIND, _UIDS[0])
        assert ecb.txnodes == {_IDS[1]: txnode} and ecb.etags == {_UIDS[0]: bind.etag}
        assert ecb.counters()["joined"] == 1 and ecb.counters()["bound"] == 1
    finally:
        ecb.close()
        link.close()
        await wire.close()


MARGIN = 1.10  #: a function's scenario may cost this much more than c/cycles.json says


def _cycles() -> tuple[ModuleType, ModuleType]:
    """c/cycles.py and c/cycles_ecb.py (make -C c cycles)."""
    sys.path.insert(0, str(C_DIR))
    try:
        import cycles
        import cycles_ecb
    finally:
        sys.path.remove(str(C_DIR))
    return cycles, cycles_ecb


@pytest.mark.parametrize(  # the full image fills 512 channels: some 30 s in the emulator
    "build", ["small", pytest.param("full", marks=pytest.mark.timeout(300))]
)
def test_no_ecb_function_costs_more_than_the_cycles_table_says(build: str) -> None:
    """c/cycles_ecb.py's CAN-ECB workload (tables filled to their bounds), and the inputs its
    search found dearest, played from c/cycles.json (no new search) on the filled tables: each
    public ups_ecb_ function's worst case within MARGIN of the figure the table gives."""
    cycles, cycles_ecb = _cycles()
    data = json.loads((C_DIR / "cycles.json").read_text())
    image = f"ecb-{build}"
    entries = data["ecb_recorded"][image]
    bound = cycles_ecb.EcbBound(build)
    played = {n: bound.play(s) for n, s in cycles.recorded_steps(entries).items()}
    lost = sorted(n for n, counts in played.items() if n not in counts)
    assert not lost, f"recorded inputs that no longer call their function (make cycles): {lost}"
    now = {n: counts[n].cycles for n, counts in played.items()}
    # the table is never below what a recorded input cost when it was written
    assert all(data["ecb"][image][n]["cycles"] >= e["cycles"] for n, e in entries.items())
    grown = {n: (entries[n]["cycles"], c) for n, c in now.items()
             if c > entries[n]["cycles"] * MARGIN}  # fmt: skip
    assert not grown, f"{image}: recorded inputs cost more (run make -C c cycles): {grown}"
    table = data["ecb_scenario"][image]
    now = {n: c.cycles for n, c in bound.finish().items()}
    assert set(now) == set(table), f"{image}: functions measured changed"
    grown = {n: (table[n]["cycles"], c) for n, c in now.items() if c > table[n]["cycles"] * MARGIN}
    assert not grown, f"{image}: worst cases grew past the table (run make -C c cycles): {grown}"


def test_a_worst_case_the_search_found_stays_when_a_later_run_does_not_find_it() -> None:
    """make -C c cycles on the small bus: each function's dearest input of a short search,
    recorded, is played again by a run that does not search at all, which finds every worst
    case of the first (the figures of c/cycles.json fall only when the code gets cheaper)."""
    _, cycles_ecb = _cycles()
    worst, _, dearest = cycles_ecb.ecb_measure("small", {}, examples=6)
    recorded = {name: steps for name, (_, steps) in dearest.items()}
    again, _, kept = cycles_ecb.ecb_measure("small", recorded, examples=0)
    found = {name: counts.cycles for name, (counts, _) in dearest.items()}
    assert {name: counts.cycles for name, (counts, _) in kept.items()} == found
    assert {name: counts.cycles for name, counts in again.items()} == {
        name: counts.cycles for name, counts in worst.items()}  # fmt: skip


@pytest.mark.parametrize("what", ["not an ELF", "a node's image"])
def test_an_image_that_is_no_can_ecb_is_refused_in_one_line(tmp_path: Path, what: str) -> None:
    """``ups c-ecb --target m0 --image`` with a file that is no CAN-ECB image (another file in
    its place, the image of a node): exit 2 and one line that names it, before any bus opens."""
    config = BUILDS["small"] if what == "not an ELF" else "minimal"
    image = tmp_path / "image" / "lib.elf"
    shutil.copytree(build_image(config).parent, image.parent)
    if what == "not an ELF":
        image.write_bytes(b"root:x:0:0:root:/root:/bin/sh\n")
    ups = Path(sys.executable).with_name("ups")
    cmd = [str(ups), "c-ecb", "--can", "virtual:never-opened", "--target", "m0", "--build",
           "small", "--image", str(image)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("ups c-ecb: "), done.stderr
    assert "Traceback" not in done.stderr
