"""can-broker, sub and pub as separate processes on one CAN bus.

Each test runs twice: over udp_multicast inside a private network namespace, and over a real
SocketCAN vcan0 (inside User-Mode Linux, see scripts/uml-run). The frames are read off the bus
by a plain python-can listener and checked against the layout in docs/protocol.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from ups import _canproto as p
from ups import name_to_uid

from .can_ecbs import KINDS, READY, can_ecb_proc
from .procs import Proc, private_multicast_bus


def drain(bus: can.BusABC) -> list[can.Message]:
    frames = []
    while (frame := bus.recv(0.2)) is not None:
        frames.append(frame)
    return frames


@pytest.mark.parametrize("kind", KINDS)
def test_broker_sub_pub_processes(mbus: str, wire: can.BusABC, tmp_path: Path, kind: str) -> None:
    """With ``ups can-broker`` and with ``ups c-ecb`` (``kind``): the same frames."""
    db = tmp_path / "ecb.db"
    with can_ecb_proc(kind, mbus, db, "--recovery", "0.2") as broker:
        broker.wait_for_line(READY)
        with Proc(
            "sub",
            "speed",
            "0x1234",
            "--can",
            mbus,
            "--count",
            "4",
            "--json",
            "--timeout",
            "30",
            "--node-id",
            "0x5B",
        ) as sub:
            sub.wait_for_line("subscribed to speed, 0x0000000000001234")
            pub = Proc(
                "pub",
                "speed",
                "0102",
                "--can",
                mbus,
                "--count",
                "3",
                "--rate",
                "100",
                "--priority",
                "0x20",
                "--node-id",
                "0x9B",
            )
            assert pub.finish()[0] == 0, pub.stderr_lines
            pub = Proc("pub", "0x1234", "", "--can", mbus, "--node-id", "0x9B")
            assert pub.finish()[0] == 0, pub.stderr_lines
            code, out = sub.finish()
            assert code == 0, sub.stderr_lines
        assert broker.stop() == 0  # SIGTERM: a clean exit

    events = [json.loads(line) for line in out.splitlines()]
    assert [e["data"] for e in events] == ["0102"] * 3 + [""]
    assert events[0]["uid"] == f"0x{name_to_uid('speed'):016x}" and events[0]["channel"] == "speed"
    assert events[3]["uid"] == "0x0000000000001234" and events[3]["channel"] is None
    assert all(e["priority"] == 0x20 for e in events[:3])

    frames = drain(wire)
    assert all(f.is_extended_id and len(f.data) <= 8 for f in frames)
    mgmt = [
        p.decode(f.arbitration_id, bytes(f.data))
        for f in frames
        if p.is_management(f.arbitration_id)
    ]
    assigned = {m.node_id: m.txnode for m in mgmt if isinstance(m, p.Assign)}
    assert assigned == {0x5B: 0, 0x9B: 1}  # the sub joined first; the pub rejoined as itself
    bound = {m.uid: m.etag for m in mgmt if isinstance(m, p.Bind)}
    speed_etag = bound[name_to_uid("speed")]
    assert speed_etag >= p.FIRST_ETAG and bound[0x1234] != speed_etag
    requests = {(m.kind, m.txnode, m.value) for m in mgmt if isinstance(m, p.Request)}
    assert (p.SUB_BIND, 0, name_to_uid("speed")) in requests
    assert (p.PUB_BIND, 1, name_to_uid("speed")) in requests
    assert (p.UNSUB, 0, name_to_uid("speed")) in requests  # the sub withdrew when it ended
    stages = [m for m in mgmt if isinstance(m, p.Stage)]
    assert stages and all(
        f.dlc == 0
        for f in frames
        if p.split_id(f.arbitration_id)[2] >> 12 == 0
        and p.split_id(f.arbitration_id)[1] == p.MGMT_TXNODE
        and p.split_id(f.arbitration_id)[0] == p.CONFIG_PRIORITY
    )
    data_frames = [f for f in frames if not p.is_management(f.arbitration_id)]
    assert [(f.arbitration_id, bytes(f.data)) for f in data_frames] == [
        (p.make_id(0x20, 1, speed_etag), b"\x01\x02")
    ] * 3 + [(p.make_id(p.DEFAULT_PRIORITY, 1, bound[0x1234]), b"")]
    # the broker's tables are on disk: a restart on the same file keeps them
    with can_ecb_proc(kind, mbus, db, "--recovery", "0.2") as broker:
        broker.wait_for_line("CAN-ECB on .*: 2 TxNodes, 2 etags bound")


def test_sub_times_out_without_events(tmp_path: Path) -> None:
    mbus = private_multicast_bus()  # the command's behaviour: one bus is enough, no kernel's
    with Proc(
        "can-broker", "--can", mbus, "--db", str(tmp_path / "ecb.db"), "--recovery", "0.2"
    ) as broker:
        broker.wait_for_line("CAN-ECB on")
        sub = Proc("sub", "quiet", "--can", mbus, "--timeout", "0.5")
        code, out = sub.finish()
        assert code == 1 and out == ""
        assert "timeout after 0 events" in "".join(sub.stderr_lines)


def test_node_without_broker_exits_with_a_clear_error() -> None:
    mbus = private_multicast_bus()
    sub = Proc("sub", "x", "--can", mbus, "--join-timeout", "0.5")
    code, _ = sub.finish()
    assert code == 2
    assert "no CAN-ECB gave this node a TxNode" in "".join(sub.stderr_lines)
