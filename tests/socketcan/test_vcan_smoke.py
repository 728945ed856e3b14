"""Smoke test of python-can's ``socketcan`` interface on a real kernel's ``vcan0``.

The host kernel of the development machines has no SocketCAN, so these tests run inside
User-Mode Linux: ``scripts/uml-run .venv/bin/python -m pytest -m socketcan``. uml-run sets
``UPS_REQUIRE_SOCKETCAN=1``, which turns a missing vcan0 into a failure instead of a skip.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap
from typing import Any

import can
import pytest

pytestmark = pytest.mark.socketcan

CHANNEL = "vcan0"
RECV_TIMEOUT = 5.0  # generous: User-Mode Linux has one slow CPU


def require_vcan0() -> None:
    # Called from the test body rather than a fixture, so that a missing vcan0 reports as a
    # failed test, not as an error in setup.
    if hasattr(socket, "AF_CAN") and os.path.exists(f"/sys/class/net/{CHANNEL}"):
        return
    reason = f"no SocketCAN {CHANNEL} here (run through scripts/uml-run)"
    if os.environ.get("UPS_REQUIRE_SOCKETCAN") == "1":
        pytest.fail(f"UPS_REQUIRE_SOCKETCAN=1 but {reason}")
    pytest.skip(reason)


def open_bus(**kwargs: Any) -> can.BusABC:
    require_vcan0()
    return can.Bus(interface="socketcan", channel=CHANNEL, **kwargs)


def test_extended_frame_between_two_buses_in_one_process() -> None:
    with open_bus() as tx, open_bus() as rx:
        tx.send(can.Message(arbitration_id=0x1ABCDE0F, is_extended_id=True, data=b"\x01\x02\xff"))
        msg = rx.recv(timeout=RECV_TIMEOUT)
    assert msg is not None, "frame sent on vcan0 never arrived on a second socket"
    assert msg.arbitration_id == 0x1ABCDE0F
    assert msg.is_extended_id
    assert bytes(msg.data) == b"\x01\x02\xff"
    assert msg.channel == CHANNEL


def test_kernel_filter_drops_non_matching_frame() -> None:
    filters = [{"can_id": 0x1ABCDE00, "can_mask": 0x1FFFFF00, "extended": True}]
    with open_bus() as tx, open_bus(can_filters=filters) as rx:
        tx.send(can.Message(arbitration_id=0x12345678, is_extended_id=True, data=b"no"))
        tx.send(can.Message(arbitration_id=0x00, is_extended_id=False, data=b"std"))
        tx.send(can.Message(arbitration_id=0x1ABCDE42, is_extended_id=True, data=b"yes"))
        # _recv_internal returns what the socket delivered, before python-can's own software
        # filter (which it silently falls back to if setting the kernel filter fails).
        # already_filtered=True says the filter is in the kernel; the first frame being the
        # matching one says the kernel dropped the two sent before it.
        msg, already_filtered = rx._recv_internal(timeout=RECV_TIMEOUT)
        assert already_filtered, "python-can fell back to software filtering"
        assert msg is not None and msg.arbitration_id == 0x1ABCDE42
        assert bytes(msg.data) == b"yes"
        assert rx.recv(timeout=0.2) is None


CHILD = textwrap.dedent(
    """
    import can
    with can.Bus(interface="socketcan", channel="vcan0") as bus:
        bus.send(can.Message(arbitration_id=0x1F000001, data=b"ready"))
        while True:
            msg = bus.recv(timeout=20)
            if msg is None:
                raise SystemExit("child: no request")
            if msg.arbitration_id == 0x1F000002:
                break
        bus.send(can.Message(arbitration_id=0x1F000003, data=bytes(reversed(msg.data))))
    """
)


def test_frames_cross_processes() -> None:
    with open_bus() as bus:
        child = subprocess.Popen([sys.executable, "-c", CHILD])
        try:
            ready = bus.recv(timeout=30)  # includes the child's start-up and `import can`
            assert ready is not None and ready.arbitration_id == 0x1F000001
            bus.send(can.Message(arbitration_id=0x1F000002, data=b"\x01\x02\x03\x04"))
            reply = bus.recv(timeout=RECV_TIMEOUT)
            assert child.wait(timeout=30) == 0
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
    assert reply is not None and reply.arbitration_id == 0x1F000003
    assert reply.is_extended_id
    assert bytes(reply.data) == b"\x04\x03\x02\x01"
