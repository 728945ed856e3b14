"""The CAN-ECB as a process: a disk that turns read-only or fills up, two buses served from one
directory, a second CAN-ECB on a bus. Nodes run in the test, over udp_multicast in a private
network namespace; the CAN-ECB's disk is a small tmpfs in a mount namespace of its own."""

from __future__ import annotations

import asyncio
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from ups import BrokerUnavailable, Node

from .can_ecbs import KINDS, READY, can_ecb_proc
from .procs import Proc, private_multicast_bus, start_tcp_broker

pytestmark = pytest.mark.netns


def _root() -> None:
    if os.geteuid() != 0:
        if os.environ.get("UPS_REQUIRE_NETNS") == "1":
            pytest.fail("needs root: mount namespaces")
        pytest.skip("needs root: mount namespaces")


@contextmanager
def ecb_on_tmpfs(bus: str, disk: Path, size: str = "1m") -> Iterator[Proc]:
    """``ups can-broker`` whose database lives on a tmpfs of ``size`` mounted at ``disk``."""
    _root()
    disk.mkdir()
    mount = 'mount -t tmpfs -o size="$1" tmpfs "$0" && shift && exec "$@"'
    prefix = ("unshare", "--mount", "--propagation", "private", "sh", "-c", mount, str(disk), size)
    with Proc(
        "can-broker", "--can", bus, "--db", f"{disk}/ecb.db", "--recovery", "0.2", prefix=prefix
    ) as ecb:
        ecb.wait_for_line("CAN-ECB on")
        yield ecb


def in_its_mounts(ecb: Proc, *command: str) -> subprocess.CompletedProcess[str]:
    """Run ``command`` in the CAN-ECB's mount namespace (where its tmpfs is)."""
    cmd = ["nsenter", "-t", str(ecb.popen.pid), "-m", *command]
    return subprocess.run(cmd, check=False, capture_output=True, text=True)


async def remount(ecb: Proc, disk: Path, mode: str) -> None:
    """Remount the CAN-ECB's disk ``mode`` (ro, rw). The kernel refuses ro while a file is open
    for writing ("mount point is busy"), as the store's writer thread holds the database for a
    moment after each request: tried again until it takes, at most 200 times (about 4 s)."""
    for _ in range(200):
        done = in_its_mounts(ecb, "mount", "-o", f"remount,{mode}", str(disk))
        if done.returncode == 0:
            return
        await asyncio.sleep(0.02)
    raise AssertionError(f"remount,{mode} of {disk} never took: {done.stderr.strip()}")


async def test_a_read_only_disk_fails_requests_clearly_and_service_resumes(tmp_path: Path) -> None:
    bus, disk = private_multicast_bus(), tmp_path / "disk"
    with ecb_on_tmpfs(bus, disk) as ecb:
        async with Node(can=bus, node_id=0x51, join_timeout=20) as node:
            sub = await node.subscribe("before")
            await remount(ecb, disk, "ro")
            with pytest.raises(BrokerUnavailable, match="database fails"):
                await node.subscribe("while/read-only")
            with pytest.raises(BrokerUnavailable, match="database fails"):  # joins too
                await Node(can=bus, node_id=0x52, join_timeout=10).start()
            await node.publish("before", b"1")  # what is bound works on
            assert (await sub.get_msg(timeout=5)).data == b"1"
            await remount(ecb, disk, "rw")
            late = await node.subscribe("while/read-only")  # the disk is back: so is the service
            async with Node(can=bus, node_id=0x52, join_timeout=20) as other:
                await other.publish("while/read-only", b"2")
                assert (await late.get_msg(timeout=5)).data == b"2"
        assert ecb.stop() == 1  # the storage errors of the run show in its exit status
    assert any("could not store" in line for line in ecb.stderr_lines)


async def test_a_full_disk_fails_requests_clearly_and_service_resumes(tmp_path: Path) -> None:
    bus, disk = private_multicast_bus(), tmp_path / "disk"
    with ecb_on_tmpfs(bus, disk, size="256k") as ecb:
        async with Node(can=bus, node_id=0x61, join_timeout=20) as node:
            await node.subscribe("before")
            in_its_mounts(ecb, "sh", "-c", f"cat /dev/zero > {disk}/fill 2>/dev/null")
            with pytest.raises(BrokerUnavailable, match="database fails"):
                await node.subscribe("while/full")
            in_its_mounts(ecb, "rm", f"{disk}/fill")
            await node.subscribe("while/full")
        assert ecb.stop() == 1
    assert any("could not store" in line for line in ecb.stderr_lines)


async def test_two_buses_served_from_one_directory_keep_their_own_files(tmp_path: Path) -> None:
    a, b = private_multicast_bus(), private_multicast_bus()
    env = {"UPS_STATE_DIR": str(tmp_path / "state")}
    with (
        Proc("can-broker", "--can", a, "--recovery", "0.2", env=env, cwd=tmp_path) as ecb_a,
        Proc("can-broker", "--can", b, "--recovery", "0.2", env=env, cwd=tmp_path) as ecb_b,
    ):
        ecb_a.wait_for_line("CAN-ECB on")
        ecb_b.wait_for_line("CAN-ECB on")
        for bus in (a, b):  # each bus is served by its own CAN-ECB
            async with Node(can=bus, node_id=0x71, join_timeout=20) as node:
                await node.subscribe(f"on/{bus}")
        again = Proc("can-broker", "--can", a, env=env, cwd=tmp_path)  # a second one for bus a
        code, _ = await asyncio.to_thread(again.finish)
        assert code == 2 and "in use by process" in "".join(again.stderr_lines)
        assert ecb_a.popen.poll() is None and ecb_b.popen.poll() is None
    assert len(list((tmp_path / "state").glob("can-ecb-*.db"))) == 2


@pytest.mark.parametrize("second", KINDS)
async def test_a_second_can_ecb_stands_by_and_takes_over_when_the_first_goes(
    tmp_path: Path, second: str
) -> None:
    """The second CAN-ECB is ``ups can-broker`` or ``ups c-ecb`` (the first, can-broker)."""
    bus = private_multicast_bus()
    db_a, db_b = str(tmp_path / "a.db"), str(tmp_path / "b.db")
    with Proc("can-broker", "--can", bus, "--db", db_a, "--recovery", "0.2") as a:
        a.wait_for_line(READY)
        async with Node(can=bus, node_id=0x81, join_timeout=20) as node:
            sub = await node.subscribe("kept")
            with can_ecb_proc(second, bus, db_b, "--recovery", "1.5") as b:
                await asyncio.to_thread(b.wait_for_line, "already serves this bus")
                await node.publish("kept", b"1")  # the first CAN-ECB and its bindings carry on
                assert (await sub.get_msg(timeout=5)).data == b"1"
                async with Node(can=bus, node_id=0x82, join_timeout=20) as late:
                    await late.subscribe("new/while/two")
                assert a.stop() == 0
                # the first is gone: the second notices, says Hello, relearns the bus and serves
                await asyncio.to_thread(b.wait_for_line, "serves the bus again", 20)
                async with Node(can=bus, node_id=0x83, join_timeout=20) as third:
                    await third.subscribe("new/after")
                    await third.publish("kept", b"2")
                    assert (await sub.get_msg(timeout=5)).data == b"2"
                    # it learnt the bus from the nodes' claims: it gave no TxNode twice ...
                    assert third.stats()["txnode"] != node.stats()["txnode"]
                # ... and contradicted no binding
                assert node.stats()["rebinds"] == 0
                assert not any("asked nothing" in line for line in b.stderr_lines)
        assert any("another CAN-ECB" in line for line in a.stderr_lines)


async def test_two_gateways_for_two_buses_from_one_directory(tmp_path: Path) -> None:
    """The gateway hosts the bus's CAN-ECB with the same per-bus default file."""
    a, b = private_multicast_bus(), private_multicast_bus()
    env = {"UPS_STATE_DIR": str(tmp_path / "state")}
    tcp, address = start_tcp_broker("--recovery", "0")
    short = ("--recovery", "0.2")  # the hosted CAN-ECBs' windows
    with (
        tcp,
        Proc("gateway", "--can", a, "--broker", address, *short, env=env, cwd=tmp_path) as gw_a,
        Proc("gateway", "--can", b, "--broker", address, *short, env=env, cwd=tmp_path) as gw_b,
    ):
        gw_a.wait_for_line("gateway .* between")
        gw_b.wait_for_line("gateway .* between")
        for bus in (a, b):
            async with Node(can=bus, node_id=0x91, join_timeout=20) as node:
                await node.subscribe(f"gw/{bus}")
        assert gw_a.popen.poll() is None and gw_b.popen.poll() is None
    assert len(list((tmp_path / "state").glob("can-ecb-*.db"))) == 2
