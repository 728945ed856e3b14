"""Errors that name the real cause, as a new user meets them with real ``ups`` processes: TLS on
one side only, a broker or router that is not there (said at once, unless asked to wait), a
virtual bus in another process, and Ctrl-C while waiting, which ends without a traceback."""

from __future__ import annotations

import re
import socket
from pathlib import Path

import pytest

from .procs import Proc, private_multicast_bus, start_tcp_broker
from .test_tls import certs

NO_NETWORK = {"UPS_BROKER": "", "UPS_CAN": "", "UPS_ZENOH": "", "UPS_CATALOG": ""}
#: a message that names a Python class ("ConnectionRefusedError", "SSLError", ...)
CLASS_NAME = re.compile(r"\b[A-Z][a-zA-Z]*(Error|Exception)\b")
#: longer than any of these commands takes when it fails at once, far shorter than the 30 s
#: they waited before, and than the --join-timeout some are given to show it is not waited
AT_ONCE = 25.0


def one_line(proc: Proc, timeout: float = AT_ONCE) -> str:
    """The process exits 2 by itself with one line of error (no traceback, no class name)."""
    code, _ = proc.finish(timeout=timeout)
    text = "".join(proc.stderr_lines)
    assert code == 2, text
    assert "Traceback" not in text and not CLASS_NAME.search(text), text
    (line,) = proc.stderr_lines
    assert line.startswith(f"ups {proc.args[0]}: "), text
    return line


def free_address() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"127.0.0.1:{s.getsockname()[1]}"  # nothing listens there now


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fleet")
    certs(folder, "ca", str(folder))
    for name in ("broker", "robot"):
        certs(folder, "issue", str(folder), name)
    return folder


def tls_options(fleet: Path, name: str) -> list[str]:
    return ["--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(fleet / f"{name}.crt"),
            "--tls-key", str(fleet / f"{name}.key")]  # fmt: skip


def test_a_plain_client_at_a_tls_broker_is_told_tls_is_expected(fleet: Path) -> None:
    broker, address = start_tcp_broker("--recovery", "0", *tls_options(fleet, "broker"))
    with broker:
        line = one_line(Proc("sub", "robot/speed", "--broker", address, "--join-timeout", "600"))
        assert f"the TCP-ECB at {address} expects TLS" in line and "--tls-ca" in line
        line = one_line(Proc("pub", "robot/speed", "01", "--broker", address))
        assert "expects TLS" in line
        line = one_line(Proc("status", address))
        assert f"the daemon at {address} expects TLS" in line


def test_a_tls_client_at_a_plain_broker_is_told_it_does_not_speak_tls(fleet: Path) -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker:
        sub = Proc("sub", "robot/speed", "--broker", address, "--join-timeout", "600",
                   *tls_options(fleet, "robot"))  # fmt: skip
        assert f"the TCP-ECB at {address} does not speak TLS" in one_line(sub)
        line = one_line(Proc("status", address, *tls_options(fleet, "robot")))
        assert "does not speak TLS" in line


def test_nothing_listening_fails_at_once_on_tcp_and_zenoh() -> None:
    address = free_address()
    line = one_line(Proc("pub", "robot/speed", "0032", "--broker", address, env=NO_NETWORK))
    assert f"nothing listens at {address} (connection refused)" in line
    assert "'ups broker --listen" in line and "--join-timeout S" in line
    endpoint = f"tcp/{free_address()}"
    sub = Proc("sub", "robot/speed", "--zenoh", endpoint, "--count", "1", "--timeout", "3",
               env=NO_NETWORK)  # fmt: skip
    line = one_line(sub)
    assert f"could not join the Zenoh router at {endpoint} (nothing answers there)" in line
    assert f"'ups zenoh-router --listen {endpoint}'" in line


def test_join_timeout_waits_for_a_broker_started_later_and_says_so_once() -> None:
    address = free_address()
    with Proc("sub", "robot/speed", "--broker", address, "--join-timeout", "120", "--count", "1",
              env=NO_NETWORK) as sub:  # fmt: skip
        sub.wait_for_line(f"waiting for the TCP-ECB at {address} \\(up to 120 s\\)")
        broker, _ = start_tcp_broker("--recovery", "0", port=int(address.rsplit(":", 1)[1]))
        with broker:
            sub.wait_for_line("subscribed to robot/speed", timeout=60)
            assert Proc("pub", "robot/speed", "0032", "--broker", address).finish()[0] == 0
            code, out = sub.finish(timeout=60)
    assert code == 0 and out.startswith("robot/speed  0032"), sub.stderr_lines
    assert sum("waiting for" in line for line in sub.stderr_lines) == 1, sub.stderr_lines


def test_a_virtual_bus_in_another_process_is_named_as_the_cause(tmp_path: Path) -> None:
    bus = f"virtual:robot-{tmp_path.name}"
    with Proc(
        "can-broker", "--can", bus, "--db", str(tmp_path / "ecb.db"), "--recovery", "0.2"
    ) as broker:
        broker.wait_for_line(f"{bus} is a python-can virtual bus, which lives inside this process")
        broker.wait_for_line("CAN-ECB on")
        line = one_line(Proc("sub", "robot/speed", "--can", bus, env=NO_NETWORK))
    assert f"{bus} is a python-can virtual bus, which lives inside one process" in line
    assert "udp_multicast" in line and "scripts/netns-run" in line and "socketcan:vcan0" in line


def interrupted(proc: Proc, waiting_for: str) -> str:
    """Ctrl-C once the command says it waits: it ends by itself, without a traceback."""
    with proc:
        proc.wait_for_line(f"waiting for {waiting_for}")
        proc.interrupt()
        proc.finish(timeout=30)
    text = "".join(proc.stderr_lines)
    assert "Traceback" not in text and not CLASS_NAME.search(text), text
    return text


def test_ctrl_c_while_waiting_for_a_broker_or_router_ends_without_a_traceback() -> None:
    address = free_address()
    interrupted(Proc("pub", "x", "01", "--broker", address, "--join-timeout", "120"),
                f"the TCP-ECB at {address}")  # fmt: skip
    endpoint = f"tcp/{free_address()}"
    interrupted(Proc("sub", "x", "--zenoh", endpoint, "--join-timeout", "120"),
                f"the Zenoh router at {endpoint}")  # fmt: skip


@pytest.mark.netns
def test_ctrl_c_while_waiting_for_a_can_ecb_ends_without_a_traceback() -> None:
    bus = private_multicast_bus()
    interrupted(Proc("sub", "x", "--can", bus), "the CAN-ECB")


def test_a_certificate_from_another_ca_is_named_on_either_side(fleet: Path, tmp_path: Path) -> None:
    """A node whose fleet CA is not the TCP-ECB's: the side that refused which certificate,
    said at once (it was 'no TCP-ECB answered ... or give --join-timeout S' after waiting)."""
    other = tmp_path / "other"
    certs(tmp_path, "ca", str(other))
    certs(tmp_path, "issue", str(other), "robot")
    broker, address = start_tcp_broker("--recovery", "0", *tls_options(fleet, "broker"))
    with broker:
        # it trusts the other CA: the TCP-ECB's certificate is refused here
        sub = Proc("sub", "robot/speed", "--broker", address, "--join-timeout", "600",
                   *tls_options(other, "robot"))  # fmt: skip
        line = one_line(sub)
        assert (
            f"the TCP-ECB at {address} shows a certificate that the CA {other / 'ca.crt'}" in line
        )
        assert "does not vouch for (certificate signature failure)" in line
        assert "one fleet CA" in line
        # it trusts the fleet's CA, its own certificate is the other CA's: refused there
        mixed = ["--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(other / "robot.crt"),
                 "--tls-key", str(other / "robot.key")]  # fmt: skip
        line = one_line(Proc("pub", "robot/speed", "01", "--broker", address, *mixed))
        assert f"refused this side's certificate {other / 'robot.crt'}" in line
        assert f"not signed by the CA {fleet / 'ca.crt'}" in line
        line = one_line(Proc("status", address, *mixed))
        assert f"the daemon at {address} refused this side's certificate" in line
