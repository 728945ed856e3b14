"""The CAN-ECB daemons the process tests run on a bus: ``ups can-broker`` (ours in Python, its
tables in SQLite), ``ups c-ecb`` (libups-ecb, the CAN-ECB in C, its tables in a blob) and
``ups c-ecb --target m0`` (the same loop on libups-ecb's Cortex-M0+ image in an emulator). All
log ``CAN-ECB on BUS`` once they serve, and the same lines when they stand by ("already serves
this bus") and take over ("serves the bus again"). A test about what any CAN-ECB does takes
its kind as a parameter (``KINDS``) and starts it with ``can_ecb_proc``; the emulated image
("m0", slower) runs the tests of tests/test_cecb_m0_processes.py, which call those tests with
it."""

from __future__ import annotations

from pathlib import Path

from .procs import Proc

KINDS = ("python", "c")  #: as in tests/conformance: ids end in [python] and [c]
M0 = "m0"  #: the kind of ``ups c-ecb --target m0`` (tests/test_cecb_m0_processes.py)
READY = "CAN-ECB on"  #: the line all log once they serve
_COMMANDS = {
    "python": ("can-broker", "--db"),
    "c": ("c-ecb", "--state"),
    M0: ("c-ecb", "--target", "m0", "--state"),
}


def can_ecb_proc(kind: str, bus: str, state: Path | str, *args: str) -> Proc:
    """The CAN-ECB daemon of ``kind`` (``KINDS`` or ``M0``) on ``bus``, its durable state in
    ``state`` (the SQLite file, or libups-ecb's blob); ``args``: options all take
    (``--recovery``, ``--status``, ``--bitrate``, ``--metrics``)."""
    *command, option = _COMMANDS[kind]
    return Proc(*command, "--can", bus, option, str(state), *args)
