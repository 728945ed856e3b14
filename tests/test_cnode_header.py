"""``ups uid`` and ``ups catalog --c-header``: the C constants compile and carry the UIDs and
layouts that the Python side computes."""

from __future__ import annotations

import contextlib
import io
import subprocess
from pathlib import Path

from ups import name_to_uid
from upscli import main

from .procs import ROOT

CATALOG = ROOT / "examples" / "robots.toml"  # robot/brake: every 50 ms, due in 2 ms


def run_ups(*args: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(list(args)) == 0
    return out.getvalue()


def test_uid_prints_c_constants() -> None:
    assert run_ups("uid", "robot/speed", "0x12") == (
        "#define UPS_UID_ROBOT_SPEED 0xeb79dab9bbb48dc7ULL /* robot/speed */\n"
        "#define UPS_UID_0000000000000012 0x0000000000000012ULL /* 0x0000000000000012 */\n"
    )


def test_catalog_header_compiles_with_the_uids_and_layouts(tmp_path: Path) -> None:
    header = tmp_path / "robots.h"
    run_ups("catalog", "--c-header", str(CATALOG), "-o", str(header))
    program = tmp_path / "check.c"
    program.write_text(
        '#include <stdio.h>\n#include "robots.h"\n#include "ups.h"\n'
        "int main(void) {\n"
        '    printf("%llx %u %u\\n", (unsigned long long)UPS_UID_ROBOT_SPEED, UPS_SIZE_ROBOT_SPEED,'
        " UPS_OFFSET_ROBOT_SPEED_SPEED);\n"
        '    printf("%llx %u %u %u\\n", (unsigned long long)UPS_UID_ROBOT_BRAKE,'
        " UPS_PERIOD_ROBOT_BRAKE, UPS_DEADLINE_ROBOT_BRAKE, UPS_JITTER_ROBOT_BRAKE);\n"
        "    return 0;\n}\n"
    )
    exe = tmp_path / "check"
    subprocess.run(
        [
            "cc",
            "-std=c99",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-pedantic",
            f"-I{ROOT / 'c'}",
            f"-I{tmp_path}",
            "-o",
            str(exe),
            str(program),
        ],
        check=True,
    )
    lines = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
    speed, brake = lines.splitlines()
    assert speed == f"{name_to_uid('robot/speed'):x} 2 0"
    assert brake == f"{name_to_uid('robot/brake'):x} 500 20 0"  # 50 ms, 2 ms, in 100 us
