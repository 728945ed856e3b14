"""TLS on every TCP link: certificates from `ups certs`, both sides authenticated, node ids
bound to identities. Real sockets on loopback; the certificates are made by the CLI."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from ups import AccessDenied, ConfigError, Node, Tls
from ups._tcpface import query_status
from ups.broker.tcp_ecb import TcpEcb

from .conftest import eventually
from .procs import ROOT, Proc


def certs(folder: Path, *args: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "upscli", "certs", *args], cwd=ROOT, capture_output=True,
        text=True, check=False, timeout=60,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fleet")
    certs(folder, "ca", str(folder))
    for name in ("broker", "alice", "bob", "mallory"):
        certs(folder, "issue", str(folder), name)
    return folder


def tls(folder: Path, name: str) -> Tls:
    return Tls(folder / "ca.crt", folder / f"{name}.crt", folder / f"{name}.key")


@pytest.fixture
async def ecb(fleet: Path) -> AsyncIterator[TcpEcb]:
    broker = TcpEcb("127.0.0.1", 0, recovery=0, tls=tls(fleet, "broker"))
    await broker.start()
    try:
        yield broker
    finally:
        await broker.close()


async def test_nodes_of_the_fleet_exchange_events_over_tls(fleet: Path, ecb: TcpEcb) -> None:
    address = f"127.0.0.1:{ecb.port}"
    async with (
        Node(broker=address, node_id=0xA1, tls=tls(fleet, "alice")) as alice,
        Node(broker=address, node_id=0xB0, tls=tls(fleet, "bob")) as bob,
    ):
        sub = await alice.subscribe("secure/speed")
        await bob.publish("secure/speed", b"\x01")
        assert (await sub.get_msg(timeout=5)).data == b"\x01"
        status = await query_status(address, tls=tls(fleet, "alice"))
        assert status["stats"]["nodes"] == 2


async def test_a_client_without_a_fleet_certificate_is_refused(
    fleet: Path, ecb: TcpEcb, tmp_path: Path
) -> None:
    address = f"127.0.0.1:{ecb.port}"
    with pytest.raises(ConfigError, match="expects TLS"):  # plain TCP: said at once
        await Node(broker=address, node_id=0xC1, join_timeout=1).start()
    certs(tmp_path, "ca", str(tmp_path))  # another CA, and a certificate from it
    certs(tmp_path, "issue", str(tmp_path), "alice")
    with pytest.raises(ConfigError, match=r"shows a certificate that the CA .* does not vouch"):
        await Node(broker=address, node_id=0xC2, join_timeout=1, tls=tls(tmp_path, "alice")).start()
    assert ecb.stats()["nodes"] == 0


async def test_a_node_id_cannot_be_taken_by_another_identity(fleet: Path, ecb: TcpEcb) -> None:
    address = f"127.0.0.1:{ecb.port}"
    async with Node(broker=address, node_id=0xA1, tls=tls(fleet, "alice")) as alice:
        await alice.subscribe("mine")
        thief = Node(broker=address, node_id=0xA1, join_timeout=5, tls=tls(fleet, "mallory"))
        with pytest.raises(AccessDenied, match="node id 00000000000000a1 is taken"):
            await thief.start()  # at once, with the reason
        await thief.close()
        assert ecb.stats()["impostors"] == 1 and ecb.stats()["nodes"] == 1
    # alice is gone (she may be restarting): her id is still hers, for mallory to squat on.
    await eventually(lambda: ecb.stats()["nodes"] == 0)
    squatter = Node(broker=address, node_id=0xA1, join_timeout=5, tls=tls(fleet, "mallory"))
    with pytest.raises(AccessDenied, match="is taken"):
        await squatter.start()
    await squatter.close()
    async with Node(broker=address, node_id=0xA1, tls=tls(fleet, "alice")) as back:
        await back.subscribe("mine")


async def test_one_program_run_by_two_identities_gets_two_node_ids(
    fleet: Path, ecb: TcpEcb
) -> None:
    """Default ids hash the machine and the name, and with TLS the identity: alice's and then
    bob's run of one program are two nodes, not one id claimed by two identities."""
    ids = []
    for who in ("alice", "bob"):
        async with Node(broker=f"127.0.0.1:{ecb.port}", name="same", tls=tls(fleet, who)) as n:
            await n.subscribe("x")
            ids.append(n.node_id)
    assert ids[0] != ids[1] and ecb.stats()["impostors"] == 0


def test_the_command_line_over_tls(fleet: Path) -> None:
    def opts(name: str) -> list[str]:
        return ["--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(fleet / f"{name}.crt"),
                "--tls-key", str(fleet / f"{name}.key")]  # fmt: skip

    with Proc("broker", "--listen", "127.0.0.1:0", "--recovery", "0", *opts("broker")) as broker:
        line = broker.wait_for_line(r"TCP-ECB on 127\.0\.0\.1:\d+")
        address = line.split("TCP-ECB on ")[1].split()[0]
        with Proc("sub", "cli/tls", "--broker", address, "--count", "1", "--timeout", "20",
                  *opts("alice")) as sub:  # fmt: skip
            sub.wait_for_line("subscribed to")
            pub = Proc("pub", "cli/tls", "07", "--broker", address, *opts("bob"))
            assert pub.finish()[0] == 0, pub.stderr_lines
            code, out = sub.finish()
            assert code == 0 and "07" in out, sub.stderr_lines
        bad = Proc("pub", "cli/tls", "07", "--broker", address, "--tls-ca", str(fleet / "ca.crt"))
        code, _ = bad.finish()
        assert code == 2 and "all of --tls-ca, --tls-cert and --tls-key" in "".join(
            bad.stderr_lines
        )


async def test_the_console_behind_tls_serves_only_fleet_browsers(fleet: Path) -> None:
    """With TLS the console's page is HTTPS, and a client without a fleet certificate gets no
    page; with one (alice's), the page and the console's view of the fleet."""
    import ssl

    import aiohttp

    def opts(name: str) -> list[str]:
        return ["--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(fleet / f"{name}.crt"),
                "--tls-key", str(fleet / f"{name}.key")]  # fmt: skip

    with Proc("broker", "--listen", "127.0.0.1:0", "--recovery", "0", *opts("broker")) as broker:
        line = broker.wait_for_line(r"TCP-ECB on 127\.0\.0\.1:\d+")
        address = line.split("TCP-ECB on ")[1].split()[0]
        with Proc("console", "--listen", "127.0.0.1:0", "--broker", address,
                  *opts("bob")) as console:  # fmt: skip
            url = console.wait_for_line(r"console on https://").split("console on ")[1].strip()
            fleet_browser = ssl.create_default_context(cafile=str(fleet / "ca.crt"))
            fleet_browser.check_hostname = False  # the certificate names an identity, not a host
            fleet_browser.load_cert_chain(fleet / "alice.crt", fleet / "alice.key")
            stranger = ssl.create_default_context(cafile=str(fleet / "ca.crt"))
            stranger.check_hostname = False
            async with aiohttp.ClientSession() as http:
                reply = await http.get(f"{url}/snapshot", ssl=fleet_browser)
                assert reply.status == 200 and (await reply.json())["source"] == address
                with pytest.raises(aiohttp.ClientError):
                    await http.get(f"{url}/snapshot", ssl=stranger)
