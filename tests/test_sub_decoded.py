"""``ups sub --catalog`` (or ``$UPS_CATALOG``) prints decoded values, as ``ups monitor`` and
``ups decode`` do: real ``ups`` processes around a real TCP-ECB."""

from __future__ import annotations

import json

from .procs import ROOT, Proc, start_tcp_broker

CATALOG = str(ROOT / "examples" / "robots.toml")
SPEED_UID = "0xeb79dab9bbb48dc7"  # robot/speed


def test_sub_prints_the_catalogs_values_plain_and_as_json() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        Proc("sub", "robot/speed", "--broker", address, "--catalog", CATALOG, "--count", "1",
             "--timeout", "30") as plain,
        Proc("sub", SPEED_UID, "--broker", address, "--json", "--count", "1", "--timeout", "30",
             env={"UPS_CATALOG": CATALOG}) as as_json,
    ):  # fmt: skip
        plain.wait_for_line("subscribed to robot/speed")
        as_json.wait_for_line(f"subscribed to {SPEED_UID}")
        code, _ = Proc("pub", "robot/speed", "0032", "--broker", address).finish()
        assert code == 0
        code, out = plain.finish(timeout=30)
        assert code == 0, plain.stderr_lines
        assert out.startswith("robot/speed  speed=50 cm/s  prio=128  from=0x"), out
        code, out = as_json.finish(timeout=30)
        assert code == 0, as_json.stderr_lines
        event = json.loads(out)
        assert event["channel"] == "robot/speed"  # subscribed by UID: the catalog names it
        assert event["values"] == {"speed": 50} and event["data"] == "0032"


def test_without_a_catalog_the_data_is_hex_and_values_null() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    env = {"UPS_CATALOG": ""}
    with (
        broker,
        Proc("sub", "robot/speed", "--broker", address, "--json", "--count", "1",
             "--timeout", "30", env=env) as sub,
    ):  # fmt: skip
        sub.wait_for_line("subscribed to robot/speed")
        code, _ = Proc("pub", "robot/speed", "0032", "--broker", address).finish()
        assert code == 0
        code, out = sub.finish(timeout=30)
        assert code == 0 and json.loads(out)["values"] is None and '"data": "0032"' in out
