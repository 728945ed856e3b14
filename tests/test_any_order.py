"""Subscribed means delivered, in the start orders a new user meets (issue 38): a pattern
subscriber on TCP/IP gets the events of channels named after it, also channels published
once; with TLS and an ACL, exactly those its identity may read."""

from __future__ import annotations

import json
from pathlib import Path

from .procs import Proc, start_tcp_broker
from .test_acl import fleet as fleet

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
    broker, address = start_tcp_broker()
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
