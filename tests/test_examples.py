"""Examples are product: the demo must run and show every channel, the brake included, on CAN
and through the gateway on TCP/IP."""

from __future__ import annotations

from .procs import Proc


def test_demo_runs_and_brakes() -> None:
    demo = Proc("demo", "--duration", "2.5")
    code, out = demo.finish(timeout=60)
    assert code == 0, "".join(demo.stderr_lines)
    assert "robot/brake admitted as real-time, priority 0x02" in out
    assert "dashboard: BRAKE from TxNode 3 (priority 0x02)" in out
    assert "wheel-encoder: speed limit 30 cm/s from TxNode 0" in out  # TCP -> gateway -> CAN
    assert "operator (TCP): BRAKE via the gateway (priority 0x02)" in out  # CAN -> TCP
    assert "gets a TxNode" in out.split("gateway:")[0]  # it says what it will show, first
    assert "In short: everything arrived." in out and "Try next" in out
