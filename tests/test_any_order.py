"""Subscribed means delivered, in the start orders a new user meets (issue 38): a pattern
subscriber on TCP/IP gets the events of channels named after it, also channels published
once (with TLS and an ACL, exactly those its identity may read); a gateway that joins a running
bus forwards what was bound before it came, to TCP/IP and to Zenoh."""

from __future__ import annotations

import contextlib
import json
import socket
from pathlib import Path

import pytest

from ups._canlink import open_bus

from .procs import Proc, private_multicast_bus, start_tcp_broker
from .test_acl import fleet as fleet
from .test_gateway_processes import event_ids
from .test_zenoh_processes import start_router

NO_ENV = {"UPS_BROKER": "", "UPS_CAN": "", "UPS_ZENOH": "", "UPS_CATALOG": ""}


def _events(sub: Proc, count: int) -> list[tuple[str, str]]:
    """(channel, data) of the first ``count`` events ``sub --json`` printed."""
    try:
        lines = sub.wait_for_stdout(count, timeout=30)
    except AssertionError as exc:
        raise AssertionError(f"{exc}; its log:\n{''.join(sub.stderr_lines[-30:])}") from None
    return [(e["channel"], e["data"]) for e in map(json.loads, lines)]


def _publish(net: tuple[str, ...], channel: str, data: str, count: int = 1,
             extra: tuple[str, ...] = (), env: dict[str, str] | None = None) -> None:  # fmt: skip
    with Proc("pub", channel, data, *net, "--count", str(count), *extra, env=env) as pub:
        code, _ = pub.finish(timeout=30)
    assert code == 0, "".join(pub.stderr_lines)


def test_a_tcp_pattern_gets_every_event_of_channels_named_after_it() -> None:
    """`ups sub 'fleet/*'`, then five channels published once each, then five three times:
    all 20 events (before: 0 of 5 and 12 of 20, nothing counted)."""
    broker, address = start_tcp_broker("--recovery", "0")
    net = ("--broker", address)
    with broker, Proc("sub", "fleet/*", *net, "--json", env=NO_ENV) as sub:
        sub.wait_for_line("subscribed to fleet/\\*")
        for n in range(5):
            _publish(net, f"fleet/c{n}", f"0{n}")
        assert sorted(_events(sub, 5)) == [(f"fleet/c{n}", f"0{n}") for n in range(5)]
        for n in range(5, 10):
            _publish(net, f"fleet/c{n}", f"0{n}", count=3)
        events = _events(sub, 20)
        sub.stop()
    assert sorted(events[5:]) == sorted((f"fleet/c{n}", f"0{n}") for n in range(5, 10)
                                        for _ in range(3))  # fmt: skip
    assert len(sub.stdout_lines) == 20  # exactly once


def test_with_tls_and_an_acl_a_pattern_gets_exactly_what_its_identity_may_read(
    fleet: Path,
) -> None:
    """alice may read robot/* and fleet/go: `ups sub '*'` as alice, then bob publishes five
    channels once each; alice gets fleet/go and robot/speed, once each, and nothing else."""

    def opts(name: str) -> tuple[str, ...]:
        return ("--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(fleet / f"{name}.crt"),
                "--tls-key", str(fleet / f"{name}.key"))  # fmt: skip

    broker, address = start_tcp_broker("--acl", str(fleet / "acl.toml"), *opts("broker"))
    net = ("--broker", address)
    with broker, Proc("sub", "*", *net, *opts("alice"), "--json", env=NO_ENV) as sub:
        sub.wait_for_line("subscribed to \\*")
        for channel in ("fleet/stop", "fleet/go", "fleet/c1", "robot/speed", "fleet/c2"):
            _publish(net, channel, "01", extra=opts("bob"))
        events = _events(sub, 2)
        _publish(net, "fleet/go", "02", extra=opts("bob"))  # and nothing else came between
        events = _events(sub, 3)
        sub.stop()
    assert sorted(events[:2]) == [("fleet/go", "01"), ("robot/speed", "01")]
    assert events[2] == ("fleet/go", "02")


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@pytest.mark.parametrize(
    ("side", "mode"),
    [("broker", "--external-can-ecb"), ("zenoh", "--external-can-ecb"), ("broker", "hosting")],
)
def test_a_gateway_that_joins_a_running_bus_forwards_what_was_bound_before_it(
    side: str, mode: str, tmp_path: Path
) -> None:
    """`ups can-broker`, a CAN publisher, then `ups gateway --external-can-ecb`: a subscriber
    on the IP side gets the publisher's events (before: 0 events, `bindings: 0`). So does a
    gateway that hosts a CAN-ECB of its own, which stands by for the one already serving."""
    bus = private_multicast_bus()
    with contextlib.ExitStack() as stack:
        if side == "broker":
            broker, where = start_tcp_broker("--recovery", "0")
            stack.enter_context(broker)
        else:
            where = _free_endpoint()
            stack.enter_context(start_router(where))
        ip = (f"--{side}", where)
        ecb = stack.enter_context(
            Proc("can-broker", "--can", bus, "--db", str(tmp_path / "e.db"), "--recovery", "0.2")
        )
        ecb.wait_for_line("CAN-ECB on")
        stack.enter_context(
            Proc("pub", "robot/speed", "0032", "--can", bus, "--count", "100000", "--rate", "20")
        )
        listener = open_bus(bus)
        stack.callback(listener.shutdown)
        event_ids(listener, 2)  # it publishes: its channel was bound before the gateway came
        own = (
            ("--db", str(tmp_path / "gw.db"), "--recovery", "0.2") if mode == "hosting" else (mode,)
        )
        gw = stack.enter_context(Proc("gateway", *own, "--can", bus, *ip, "--node-id", "0x6a7f"))
        gw.wait_for_line("gateway .* between", timeout=60)
        with Proc("sub", "robot/speed", *ip, "--json", "--count", "3", "--timeout", "20",
                  env=NO_ENV) as sub:  # fmt: skip
            code, out = sub.finish(timeout=40)
        assert code == 0, "".join(sub.stderr_lines[-20:] + gw.stderr_lines[-20:])
    assert [json.loads(line)["data"] for line in out.splitlines()] == ["0032"] * 3


def test_a_subscriber_started_before_its_tcp_ecb_gets_every_event() -> None:
    """`ups sub ... --join-timeout 15`, then the TCP-ECB, then a publisher: every event."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    net = ("--broker", f"127.0.0.1:{port}")
    with Proc("sub", "robot/speed", "fleet/*", *net, "--json", "--join-timeout", "15",
              "--count", "6", "--timeout", "40", env=NO_ENV) as sub:  # fmt: skip
        sub.wait_for_line("waiting for the TCP-ECB")
        broker, _ = start_tcp_broker(port=port)
        with broker:
            sub.wait_for_line("subscribed to")
            _publish(net, "robot/speed", "0032", count=3, extra=("--rate", "50"))
            _publish(net, "fleet/c1", "01")
            _publish(net, "fleet/c2", "02", count=2)
            code, out = sub.finish(timeout=40)
    assert code == 0, "".join(sub.stderr_lines[-10:])
    events = sorted((e["channel"], e["data"]) for e in map(json.loads, out.splitlines()))
    assert events == [("fleet/c1", "01"), ("fleet/c2", "02"), ("fleet/c2", "02"),
                      *[("robot/speed", "0032")] * 3]  # fmt: skip
