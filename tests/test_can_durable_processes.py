"""Issue 32, CAN: the CAN-ECB's table survives losing its file while the CAN-ECB runs. The
attack: the database deleted while ``ups can-broker`` ran, the daemon stopped before its next
write: at the next start every TxNode and etag was given anew. Now the CAN-ECB writes all it
knows again when it notices (within a second, and when it stops), before it serves on.

The CAN-ECB runs as a process (it must stop and start again); nodes run in the test, over
udp_multicast in a private network namespace."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from ups import Node, name_to_uid
from ups._canface import CanFace

from .procs import Proc, private_multicast_bus

pytestmark = pytest.mark.netns

IDS = [0xD0, 0xD1, 0xD2]
NAMES = [f"durable/{i}" for i in range(6)]


async def assignments(bus: str, ids: list[int], names: list[str]) -> dict[int, tuple[int, ...]]:
    """Each node in turn joins and subscribes to ``names``, in this order; node id -> its TxNode
    and the etags it was given (in the order of ``NAMES``)."""
    got = {}
    for node_id in ids:
        async with Node(can=bus, node_id=node_id, join_timeout=20) as node:
            await node.subscribe(*names)
            face = node.face
            assert isinstance(face, CanFace)
            etags = tuple(face.bindings.bound[name_to_uid(n)] for n in NAMES)
            got[node_id] = (node.stats()["txnode"], *etags)
    return got


def can_broker(bus: str, db: Path) -> Proc:
    return Proc("can-broker", "--can", bus, "--db", str(db), "--recovery", "0.2")


@pytest.mark.parametrize("stop", ["stopped", "killed"])
async def test_a_database_deleted_while_the_can_ecb_runs_loses_nothing(
    tmp_path: Path, stop: str
) -> None:
    bus, db = private_multicast_bus(), tmp_path / "ecb.db"
    with can_broker(bus, db) as ecb:
        ecb.wait_for_line("CAN-ECB on")
        before = await assignments(bus, IDS, NAMES)
        db.unlink()
        if stop == "killed":  # it wrote the file again: nothing is lost even without a goodbye
            await asyncio.to_thread(ecb.wait_for_line, "written anew", 10)
            ecb.kill()
        else:  # at once, before anything made it write
            ecb.stop()
    assert db.exists()
    with can_broker(bus, db) as ecb:
        ecb.wait_for_line("CAN-ECB on .*: 3 TxNodes, 6 etags bound")
        # in the other order: a new table would give the first node TxNode 0 and etag 0x10
        after = await assignments(bus, IDS[::-1], NAMES[::-1])
    assert after == before
