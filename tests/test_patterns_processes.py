"""``ups sub 'robot/*'`` as a new user types it, with real processes on every network that knows
names: a TCP-ECB, a Zenoh router, and a CAN bus (udp_multicast in a private namespace) whose
names come from the catalog. Channels named later join; no silent literal anywhere."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

import pytest

from .procs import ROOT, Proc, private_multicast_bus, start_tcp_broker
from .test_zenoh_processes import start_router

CATALOG = str(ROOT / "examples" / "robots.toml")
NO_ENV = {"UPS_BROKER": "", "UPS_CAN": "", "UPS_ZENOH": "", "UPS_CATALOG": ""}


def events_until(sub: Proc, channel: str, most: int = 2000) -> list[dict[str, Any]]:
    """The JSON events ``sub`` printed, once one of ``channel`` is among them."""
    seen = 0
    while True:
        lines = sub.wait_for_stdout(seen + 1, timeout=60)
        events = [json.loads(line) for line in lines]
        if any(e["channel"] == channel for e in events):
            return events
        seen = len(lines)
        assert seen < most, f"no event of {channel} in {seen}"


def test_tcp_ups_sub_of_a_pattern_prints_every_matching_channel_named_now_or_later() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    net = ("--broker", address)
    with (
        broker,
        Proc("pub", "robot/speed", "0032", *net, "--count", "100000", "--rate", "20") as speed,
        Proc("pub", "other/x", "01", *net, "--count", "100000", "--rate", "20") as other,
    ):
        with Proc("sub", "robot/*", *net, "--json", env=NO_ENV) as sub:
            line = sub.wait_for_line("subscribed to robot/\\*")
            assert "more join as they are named" in line
            events_until(sub, "robot/speed")
            with Proc("pub", "robot/distance", "00c8", *net, "--count", "100000",
                      "--rate", "20") as later:  # fmt: skip
                events = events_until(sub, "robot/distance")
                later.stop()
            sub.stop()
        speed.stop()
        other.stop()
    assert {e["channel"] for e in events} == {"robot/speed", "robot/distance"}
    assert "Traceback" not in "".join(sub.stderr_lines)


def test_zenoh_ups_sub_of_a_pattern_prints_every_matching_channel() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    net = ("--zenoh", endpoint)
    with (
        start_router(endpoint),
        Proc("sub", "robot/*", *net, "--json", "--catalog", CATALOG, env=NO_ENV) as sub,
    ):
        sub.wait_for_line("subscribed to robot/\\* \\(no channel yet")
        with (
            Proc("pub", "other/x", "01", *net, "--count", "100000", "--rate", "20") as other,
            Proc("pub", "robot/speed", "0032", *net, "--count", "100000", "--rate", "20"),
        ):
            events = events_until(sub, "robot/speed")
            with Proc("pub", "robot/brake", "01", *net, "--count", "100000", "--rate", "20"):
                events = events_until(sub, "robot/brake")
            other.stop()
        sub.stop()
    assert {e["channel"] for e in events} == {"robot/speed", "robot/brake"}
    speed = next(e for e in events if e["channel"] == "robot/speed")
    assert speed["values"] == {"speed": 50}  # and decoded, by the catalog


@pytest.mark.netns
def test_can_ups_sub_of_a_pattern_takes_the_catalogs_channels(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    net = ("--can", bus)
    refused = Proc("sub", "robot/*", *net, env=NO_ENV)  # no catalog: refused before joining
    code, _ = refused.finish(timeout=25)
    assert code == 2 and len(refused.stderr_lines) == 1, refused.stderr_lines
    assert "on CAN, channel names come only from a channel catalog" in refused.stderr_lines[0]
    with Proc("can-broker", *net, "--db", str(tmp_path / "ecb.db"), "--recovery", "0.2") as ecb:
        ecb.wait_for_line("CAN-ECB on")
        with Proc("sub", "robot/*", *net, "--json", env={**NO_ENV, "UPS_CATALOG": CATALOG}) as sub:
            line = sub.wait_for_line("subscribed to robot/\\*", timeout=60)
            assert "robot/brake" in line and "robot/speed" in line
            with Proc("pub", "robot/brake", "01", *net, "--count", "100000", "--rate", "20"):
                events = events_until(sub, "robot/brake")
            sub.stop()
    brake = next(e for e in events if e["channel"] == "robot/brake")
    assert brake["values"] == {"brake": 1}
