"""Every TOML file UPS reads (a catalog, an ACL, the JAUS, ROS 2 and EtherCAT maps), given as a
file a user could point it at by mistake or on purpose: nested 5,000 deep, ``/dev/zero``, a
FIFO, a file too large, bytes that are not UTF-8. Each is refused at once with one line and
exit 2, by the real commands (issue 41: a RecursionError traceback, a MemoryError after
5 s, a hang)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from ups._tomlfile import MAX_BYTES

from .procs import Proc
from .test_errors_named import one_line
from .test_tls import certs

NO_NETWORK = {"UPS_BROKER": "", "UPS_CAN": "", "UPS_ZENOH": "", "UPS_CATALOG": ""}
BAD = {
    "deep": "nested too deep to read",
    "zero": "not a regular file",
    "fifo": "not a regular file",
    "huge": f"larger than {MAX_BYTES >> 20} MiB",
    "latin1": "not UTF-8",
}


def bad_file(tmp_path: Path, kind: str) -> str:
    path = tmp_path / f"{kind}.toml"
    if kind == "deep":
        path.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    elif kind == "zero":
        return "/dev/zero"
    elif kind == "fifo":
        os.mkfifo(path)  # nobody writes: reading it would wait forever
    elif kind == "huge":
        with path.open("w") as f:
            f.write("# a comment\n" * (MAX_BYTES // 12 + 1))
    else:
        path.write_bytes('description = "Geschwindigkeit \xfcber Grund"\n'.encode("latin-1"))
    return str(path)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fleet")
    certs(folder, "ca", str(folder))
    certs(folder, "issue", str(folder), "broker")
    return folder


def commands(path: str, fleet: Path) -> dict[str, list[str]]:
    tls = ["--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(fleet / "broker.crt"),
           "--tls-key", str(fleet / "broker.key")]  # fmt: skip
    return {
        "catalog": ["sub", "x", "--catalog", path, "--broker", "127.0.0.1:1"],
        "acl": ["broker", "--listen", "127.0.0.1:0", "--acl", path, *tls],
        "jaus map": ["jaus", "check", path],
        "ros2 map": ["ros2", "check", path],
        "ethercat map": ["ethercat", "check", path],
    }


@pytest.mark.parametrize("kind", sorted(BAD))
@pytest.mark.parametrize("reader", ["catalog", "acl", "jaus map", "ros2 map", "ethercat map"])
def test_a_bad_toml_file_is_one_line_and_exit_2(
    tmp_path: Path, fleet: Path, kind: str, reader: str
) -> None:
    if reader == "ros2 map":
        pytest.importorskip("rosbags", reason="the ros2 extra is not installed")
    path = bad_file(tmp_path, kind)
    args = commands(path, fleet)[reader]
    line = one_line(Proc(*args, env=NO_NETWORK))
    assert path in line and BAD[kind] in line, line
