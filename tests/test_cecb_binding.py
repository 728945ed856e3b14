"""The ctypes binding of libups-ecb (broker/_cecb_lib.py) and ``ups c-ecb``: the binding agrees with
the headers and the Makefile it is built by, names its build errors, keeps a refused blob aside,
writes the state file before it sends what the state announces; the command's help and errors.
What the C CAN-ECB does on the wire is the conformance suite's (tests/conformance, [c])."""

from __future__ import annotations

import asyncio
import re
import shutil
from pathlib import Path

import pytest

from ups import Node
from ups._canlink import CanLink
from ups._cnode import build
from ups._errors import ConfigError
from ups.broker import _cecb_lib
from ups.broker._quota import QUOTA
from ups.broker.c_ecb import CEcb

from .conformance._wire import RawNode, Wire
from .procs import ROOT, Proc, private_multicast_bus, sanitizer_env

C = ROOT / "c"


def _makefile(name: str) -> list[str]:
    """A variable of c/Makefile, its continuation lines joined, split into words."""
    text = (C / "Makefile").read_text().replace("\\\n", " ")
    match = re.search(rf"^{name} :=(.*)$", text, re.M)
    assert match, name
    return match.group(1).split()


def _struct_fields(header: str, name: str) -> list[str]:
    """The field names of ``typedef struct { ... } name;`` in ``header``, in order."""
    text = re.sub(r"/\*.*?\*/", "", (C / header).read_text(), flags=re.S)
    body = re.search(r"typedef struct \{([^}]*)\}\s*" + name + ";", text)
    assert body, name
    return re.findall(r"(\w+)(?:\[\w+\])?;", body.group(1))


def _define(header: str, name: str) -> int:
    match = re.search(rf"#define {name} (\w+)", (C / header).read_text())
    assert match, name
    return int(match.group(1).rstrip("u"), 0)


def test_sources_are_the_makefiles() -> None:
    built = {*_makefile("ECB_SRC"), *_makefile("ECB_HDR"), "host/ups_ecb_host.c", "Makefile"}
    assert set(_cecb_lib.SOURCES) == built


def test_counters_are_ups_ecb_counters_t_in_order() -> None:
    assert list(_cecb_lib.COUNTERS) == _struct_fields("ups_ecb.h", "ups_ecb_counters_t")


def test_constants_are_the_headers() -> None:
    for name in ("EXT", "FD", "BRS", "RTR", "ERR"):
        assert getattr(_cecb_lib, f"FRAME_{name}") == _define("ups.h", f"UPS_FRAME_{name}")
    for name in ("STATE", "ROLE", "CHANNELS"):
        assert getattr(_cecb_lib, f"NOTE_{name}") == _define("ups_ecb.h", f"UPS_ECB_NOTE_{name}")
    for i, role in enumerate(_cecb_lib.ROLES):
        assert _define("ups_ecb.h", f"UPS_ECB_{role.upper()}") == i
    fields = [f for f, _ in _cecb_lib.Config._fields_]
    assert fields == _struct_fields("ups_ecb.h", "ups_ecb_config_t")


def test_the_full_build_has_the_tables_of_a_full_bus() -> None:
    """With room for the default quota of a node id (1024 channels of size class 0), which
    the conformance suite fills."""
    lib = _cecb_lib.load("full")
    macros = dict(m[2:].split("=") for m in _makefile("ECB_HOST"))
    names = {"nodes": "NODES", "channels": "CHANNELS", "streams": "STREAMS",
             "queries": "QUERIES", "tx_depth": "TX_DEPTH", "held": "HELD",
             "watched": "WATCHED"}  # fmt: skip
    for key, macro in names.items():
        assert lib.config[key] == int(macros[f"UPS_ECB_{macro}"]), key
    assert lib.config["rosters"] == _define("ups_ecb.h", "UPS_ECB_ROSTERS")  # its default
    cfg = lib.config
    assert cfg["channels"] > QUOTA[0] and cfg["nodes"] == 127
    assert cfg["blob_max"] >= 12 * (cfg["nodes"] + cfg["channels"] + cfg["streams"])
    assert cfg["counter_bytes"] == 4 and cfg["mtu"] == 8
    assert lib.size > cfg["tx_depth"] * 12  # its TX queue of ups_frame_t alone
    assert _cecb_lib.default_config().recovery_ms == 2000


def test_an_unknown_variant_and_a_failed_build_are_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no variant 'tiny' .*full, asan"):
        _cecb_lib.load("tiny")
    with pytest.raises(ConfigError, match="LD_PRELOAD"):  # not an ASan abort of the process
        _cecb_lib.load("asan")
    copy = tmp_path / "c"
    shutil.copytree(C, copy, ignore=shutil.ignore_patterns("build"))
    with (copy / "ups_ecb_elect.c").open("a") as source:
        source.write("\n#error this source is broken on purpose\n")
    with pytest.raises(ConfigError) as failed:
        build("full", targets=_cecb_lib.VARIANTS, sources=_cecb_lib.SOURCES, c_dir=copy)
    assert "libups-ecb.so" in str(failed.value)
    assert "broken on purpose" in str(failed.value)


async def test_a_refused_blob_is_kept_aside(tmp_path: Path) -> None:
    state = tmp_path / "ecb.state"
    state.write_bytes(b"not a blob of libups-ecb")
    link = CanLink.open(f"virtual:cecb-refused-{id(state)}")
    ecb = CEcb(link, state, recovery=0.2)
    try:
        await ecb.start()
        assert (tmp_path / "ecb.state.bad").read_bytes() == b"not a blob of libups-ecb"
        assert ecb.counters()["blob_refused"] == 1 and not ecb.restored
        assert state.read_bytes() != b"not a blob of libups-ecb"  # its own, empty tables
    finally:
        ecb.close()
        link.close()


async def test_an_unwritable_state_file_is_an_error_at_start(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    link = CanLink.open(f"virtual:cecb-unwritable-{id(tmp_path)}")
    ecb = CEcb(link, tmp_path / "file" / "ecb.state")
    try:
        with pytest.raises(ConfigError, match=r"state file .*ecb\.state"):
            await ecb.start()
    finally:
        ecb.close()
        link.close()


async def test_the_state_is_written_before_the_frames_that_announce_it(tmp_path: Path) -> None:
    """Every frame goes out only once the file holds the tables as they were when it was
    queued; a CAN-ECB restarted from that file has the node's TxNode."""
    channel = f"cecb-durable-{id(tmp_path)}"
    state = tmp_path / "ecb.state"
    wire = Wire(channel)
    link = CanLink.open(f"virtual:{channel}")
    ecb = CEcb(link, state, recovery=0.2)
    behind: list[int] = []

    def sent(can_id: int, data: bytes) -> None:
        if state.read_bytes() != ecb.blob():
            behind.append(can_id)

    ecb.on_sent = sent
    try:
        await ecb.start()
        txnode = await RawNode(wire, 0xD0AB1E).join()
        assert ecb.txnodes == {0xD0AB1E: txnode}
        assert not behind, [f"{i:#x}" for i in behind]
    finally:
        ecb.close()
        link.close()
    link = CanLink.open(f"virtual:{channel}")
    again = CEcb(link, state, recovery=0.2)
    try:
        await again.start()
        assert again.restored and again.txnodes == {0xD0AB1E: txnode}
    finally:
        again.close()
        link.close()
        await wire.close()


# --- ups c-ecb --------------------------------------------------------------------------------


def test_help() -> None:
    with Proc("c-ecb", "--help") as proc:
        code, out = proc.finish()
    assert code == 0
    for option in ("--can", "--state", "--recovery", "--bitrate", "--status", "--metrics"):
        assert option in out


@pytest.mark.parametrize(
    ("args", "error"),
    [
        (("--can", "nonsense"), "bad CAN bus 'nonsense'"),
        (("--can", "virtual:x", "--recovery", "0.01"), "the recovery window is 0.1 to 10 s"),
        (("--can", "virtual:x", "--state", "/dev/null/ecb"), "state file /dev/null/ecb"),
    ],
    ids=["bus", "recovery", "state"],
)
def test_errors_are_said(args: tuple[str, ...], error: str) -> None:
    with Proc("c-ecb", *args) as proc:
        code, _ = proc.finish()
    assert code == 2
    assert error in "".join(proc.stderr_lines)


def test_ctrl_c_ends_it_and_leaves_the_state_file(tmp_path: Path) -> None:
    state = tmp_path / "ecb.state"
    with Proc("c-ecb", "--can", "virtual:cecb-ctrl-c", "--state", str(state)) as proc:
        proc.wait_for_line(r"CAN-ECB on .*in C.* instance [0-9a-f]{16}")
        proc.interrupt()
        code, _ = proc.finish()
    assert code == 130
    assert state.exists() and not Path(f"{state}.tmp").exists()


@pytest.mark.netns
async def test_the_sanitizer_build_serves_a_node(tmp_path: Path) -> None:
    """``ups c-ecb --build asan`` (AddressSanitizer, UndefinedBehaviorSanitizer: an error
    ends it with 99 or 98): a node joins, binds, publishes to itself; Ctrl-C saves the blob."""
    bus, state = private_multicast_bus(), tmp_path / "ecb.state"
    with Proc("c-ecb", "--can", bus, "--state", str(state), "--recovery", "0.2", "--build",
              "asan", env=sanitizer_env()) as ecb:  # fmt: skip
        await asyncio.to_thread(ecb.wait_for_line, "CAN-ECB on .*libups-ecb-asan", 60)
        async with Node(can=bus, node_id=0xA5A, join_timeout=20) as node:
            sub = await node.subscribe("asan/echo")
            await node.publish("asan/echo", b"\x01")
            assert (await sub.get_msg(timeout=5)).data == b"\x01"
        ecb.interrupt()
        code, _ = await asyncio.to_thread(ecb.finish)
    assert code == 130, "".join(ecb.stderr_lines[-20:])
    assert state.stat().st_size > 0
