"""``ups c-ecb --target m0``: the C CAN-ECB's Cortex-M0+ image (ecb-full, a bus of 127 nodes) in
the emulator as the bus's CAN-ECB (issue 42), in the private network namespace on
udp_multicast.

The process tests of the other CAN-ECBs, run with it (``tests/can_ecbs.py``'s ``M0``): nodes
join, bind and exchange events through it and it restarts on its state file; with only
microcontroller code on the bus (the node's image too); it stands by beside a serving CAN-ECB
and takes over when that one goes; ``ups ls`` reads its tables. Then what only the emulator
shows: a fault of the image (a test build whose 64-bit multiply helper reads a word at an odd
address, which the host build's would never do) ends the daemon with the address, exit code 1.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from pathlib import Path

import can
import pytest

from ups import BrokerUnavailable, Node
from ups._armnode import build_image

from . import test_can_ecb_processes, test_cnode_processes, test_ls, test_multiprocess
from .can_ecbs import M0, READY, can_ecb_proc
from .procs import Proc, private_multicast_bus
from .test_cnode_m0_processes import m0_c_node

pytest.importorskip("unicorn")


def test_help_says_what_it_runs() -> None:
    with Proc("c-ecb", "--help") as proc:
        code, out = proc.finish()
    assert code == 0
    text = " ".join(out.split())
    assert "--target {host,m0}" in text and "Cortex-M0+ image" in text and "--image ELF" in text


@pytest.mark.parametrize(
    ("args", "error"),
    [
        (("--target", "m0", "--build", "asan"), "--target m0 runs --build full or small"),
        (("--build", "small"), "--target host runs --build full or asan"),
        (("--image", "x.elf"), "--image is for --target m0"),
        (("--target", "m0", "--image", "/nonexistent/lib.elf"), "was not linked by"),
    ],
    ids=["asan-on-m0", "small-on-host", "image-on-host", "image-not-linked"],
)
def test_what_does_not_fit_the_target_is_said(args: tuple[str, ...], error: str) -> None:
    with Proc("c-ecb", "--can", "virtual:cecb-m0-args", *args) as proc:
        code, _ = proc.finish()
    assert code == 2
    assert error in "".join(proc.stderr_lines)


@pytest.mark.netns
def test_nodes_join_bind_and_exchange_events_through_it_and_it_restarts_on_its_state(
    mbus: str, wire: can.BusABC, tmp_path: Path
) -> None:
    """``ups sub`` and ``ups pub``: the frames on the wire those of the other CAN-ECBs; then
    a restart on its state file has both TxNodes and both etags."""
    test_multiprocess.test_broker_sub_pub_processes(mbus, wire, tmp_path, M0)


@pytest.mark.netns
def test_a_bus_of_cortex_m0_images_only_with_python_tools(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The node's image (``ups c-node --target m0``, as test_cnode_m0_processes runs it) and
    the CAN-ECB's image, both emulated, beside ``ups sub`` and ``ups pub``."""
    started: list[int] = []
    monkeypatch.setattr(test_cnode_processes, "c_node", m0_c_node(started))
    test_cnode_processes.test_c_node_and_python_tools_on_can(tmp_path, M0)
    assert len(started) == 2


@pytest.mark.netns
async def test_it_stands_by_and_takes_over_when_the_serving_can_ecb_goes(tmp_path: Path) -> None:
    await test_can_ecb_processes.test_a_second_can_ecb_stands_by_and_takes_over_when_the_first_goes(
        tmp_path, M0
    )


@pytest.mark.netns
def test_ls_reads_its_tables(tmp_path: Path) -> None:
    test_ls.test_ls_of_a_can_bus_asks_the_can_ecb_for_who_subscribes(tmp_path, M0)


#: libgcc's 64-bit product (ups_ecb_rt_admit's), replaced in a test build by one that also
#: reads a word at an odd address: the host build has no such helper, an M0+ faults on it
_FAULTY = r"""
#include <stdint.h>
uint64_t __aeabi_lmul(uint64_t a, uint64_t b);
uint64_t __aeabi_lmul(uint64_t a, uint64_t b)
{
    uintptr_t at = 0x20000002u;
    __asm__ volatile("" : "+r"(at)); /* an address gcc cannot see is odd: one LDR, not 4 LDRBs */
    return a + b + *(const volatile uint32_t *)at;
}
"""


@pytest.mark.netns
async def test_a_fault_of_the_image_ends_it_with_the_address(tmp_path: Path) -> None:
    """A node joins and binds (no 64-bit product: all is well); its DECLARE runs the admission
    test, whose helper faults: the daemon says the call, the address and the instruction, and
    ends with exit code 1, its state file as it last wrote it."""
    source = tmp_path / "faulty_lmul.c"
    source.write_text(_FAULTY)
    elf = build_image("ecb-full", (source,))
    helper = re.search(r"^([0-9a-f]+) T __aeabi_lmul$", _nm(elf), re.M)
    assert helper is not None, "the test build does not link the faulty helper"
    bus, state = private_multicast_bus(), tmp_path / "ecb.state"
    with can_ecb_proc(M0, bus, state, "--recovery", "0.2", "--image", str(elf)) as ecb:
        await asyncio.to_thread(ecb.wait_for_line, READY, 60)
        async with Node(can=bus, node_id=0xFA17, join_timeout=20) as node:
            await node.advertise("rt/speed")
            written = state.read_bytes()
            declaring = asyncio.ensure_future(
                node.declare("rt/speed", period_ms=10, deadline_ms=10)
            )
            code, _ = await asyncio.to_thread(ecb.finish, 60)
            declaring.cancel()  # unanswered: the CAN-ECB is gone
            with contextlib.suppress(asyncio.CancelledError, BrokerUnavailable):
                await declaring
    said = "".join(ecb.stderr_lines)
    assert code == 1, said
    assert "Traceback" not in said
    (line,) = [x for x in ecb.stderr_lines if "code stopped" in x]
    pc = int(helper.group(1), 16) & ~1
    assert re.search(r"ups_ecb_rx: an unaligned 4-byte read .*at 0x20000002 by the "
                     r"instruction at 0x([0-9a-f]{8})", line), line  # fmt: skip
    at = int(line.split("by the instruction at 0x")[1][:8], 16)
    assert pc <= at < pc + 64, (hex(pc), line)  # in the faulty helper
    assert state.read_bytes() == written  # nothing written after the fault


def _nm(elf: Path) -> str:
    import subprocess

    return subprocess.run(["arm-none-eabi-nm", str(elf)], capture_output=True, text=True,
                          check=True).stdout  # fmt: skip
