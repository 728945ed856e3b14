"""Examples are product: the demo must run and show every channel, the brake included."""

from __future__ import annotations

from .procs import Proc


def test_demo_runs_and_brakes() -> None:
    demo = Proc("demo", "--duration", "2.5")
    code, out = demo.finish(timeout=60)
    assert code == 0, "".join(demo.stderr_lines)
    assert "robot/brake admitted as real-time, priority 0x02" in out
    assert "dashboard: BRAKE from TxNode 2 (priority 0x02)" in out
