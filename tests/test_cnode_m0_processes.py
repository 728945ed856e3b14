"""The interop process tests of ``ups c-node`` again, with the Cortex-M0+ image a board flashes
run in an emulator (``--target m0``, issue 42): Python -> C and C -> Python beside ``ups sub``
and ``ups pub``, a join storm of C and Python nodes, and a CAN-ECB restart with a fresh
database, in the private network namespace on udp_multicast.

Each test is the one of ``test_cnode_processes``, run with every ``ups c-node`` it starts given
``--target m0``: nothing in the tests is special-cased for the image.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from . import test_cnode_processes as host
from .can_ecbs import KINDS
from .procs import Proc

pytest.importorskip("unicorn")
pytestmark = pytest.mark.netns


def m0_c_node(started: list[int]) -> Callable[..., Proc]:
    """``test_cnode_processes.c_node`` on the emulated Cortex-M0+ image (minimal): each node id
    it starts is added to ``started``."""

    def c_node(bus: str, node_id: int, *args: str) -> Proc:
        started.append(node_id)
        return Proc("c-node", "--target", "m0", "--build", "min", "--can", bus, "--node-id",
                    hex(node_id), *args)  # fmt: skip

    return c_node


@pytest.fixture(autouse=True)
def m0(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Every ``ups c-node`` of the host tests runs the emulated Cortex-M0+ image (minimal)."""
    started: list[int] = []
    monkeypatch.setattr(host, "c_node", m0_c_node(started))
    yield
    assert started, "the test started no ups c-node"


@pytest.mark.parametrize("ecb", KINDS)  # [c]: a bus of microcontrollers' code only
def test_m0_image_and_python_tools_on_can(tmp_path: Path, ecb: str) -> None:
    host.test_c_node_and_python_tools_on_can(tmp_path, ecb)


def test_join_storm_of_m0_images_and_python_nodes(tmp_path: Path) -> None:
    host.test_join_storm_of_c_and_python_nodes(tmp_path)


def test_can_broker_restarts_with_a_fresh_database_no_wrong_delivery(tmp_path: Path) -> None:
    host.test_can_broker_restarts_no_wrong_delivery(tmp_path, keep_db=False, ecb="python")
