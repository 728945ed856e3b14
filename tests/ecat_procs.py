"""Helpers of the EtherCAT process tests: a veth pair in the private namespace, the tests' slave
emulator (tests/ecat) as a process on one end, and its control socket."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from .procs import Proc, private_network

#: the slaves of examples/robot.ethercat.toml: an I/O terminal and a drive
SLAVES = (
    "vendor=0x2,product=0x7d23052,revision=0x00110000,name=EL-test-io,outputs=4,inputs=4",
    "vendor=0x5a5,product=0x1234,revision=3,name=UPS drive,outputs=2,inputs=6",
)
_pairs = itertools.count()


@contextlib.contextmanager
def veth_pair() -> Iterator[tuple[str, str]]:
    """A veth pair in our (private) namespace: (the master's end, the slaves' end)."""
    private_network()  # refuses (skips or fails) outside a private namespace
    if os.geteuid() != 0:
        pytest.skip("needs root: a veth pair and raw sockets")
    tag = f"{os.getpid() % 100000}x{next(_pairs)}"
    master, slaves = f"ecm{tag}", f"ecs{tag}"
    subprocess.run(["ip", "link", "add", master, "type", "veth", "peer", "name", slaves],
                   check=True)  # fmt: skip
    try:
        for end in (master, slaves):
            subprocess.run(["ip", "link", "set", end, "up"], check=True)
        yield master, slaves
    finally:
        subprocess.run(["ip", "link", "del", master], check=False, capture_output=True)


@contextlib.contextmanager
def emulator(
    ifname: str, *slaves: str, control: Path | None = None, watchdog: float = 0.0
) -> Iterator[Proc]:
    """The emulated slaves on ``ifname``, listening once this yields (their SyncManager
    watchdog: ``watchdog`` s, 0 for none)."""
    command = [sys.executable, "-m", "tests.ecat", "--ifname", ifname, "--watchdog", str(watchdog)]
    for slave in slaves:
        command += ["--slave", slave]
    if control is not None:
        command += ["--control", str(control)]
    line = " ".join(f"'{word}'" for word in command)
    with Proc(shell=f"exec {line}", env={}) as proc:
        proc.wait_for_line(rf"^ready {ifname} {len(slaves)}$", stdout=True)
        yield proc


class Control:
    """The emulator's control socket: set a slave's inputs, read its status."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path) + ".me")
        self._sock.settimeout(10)

    def ask(self, text: str) -> str:
        self._sock.sendto(text.encode(), self.path)
        return self._sock.recv(65536).decode()

    def inputs(self, position: int, hexdata: str) -> None:
        assert self.ask(f"inputs {position} {hexdata}") == "ok"

    def status(self, position: int) -> dict[str, Any]:
        return dict(json.loads(self.ask(f"status {position}")))

    def close(self) -> None:
        self._sock.close()
