"""``ups ls --broker``: the network's nodes and channels by name, with real processes."""

from __future__ import annotations

import json

from .procs import Proc
from .test_tcp_processes import start_tcp_broker, wait_until


def test_ls_shows_nodes_and_channels_by_name() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        Proc("sub", "robot/speed", "0x1234", "--broker", address) as sub,
        Proc("pub", "robot/speed", "01", "--broker", address, "--count", "1000") as pub,
    ):
        sub.wait_for_line("subscribed to")
        pub.wait_for_line("registered with the TCP-ECB")

        def listed() -> dict:
            ls = Proc("ls", "--broker", address, "--json")
            code, out = ls.finish()
            assert code == 0, ls.stderr_lines
            return json.loads(out)

        wait_until(lambda: any(c["publishers"] for c in listed()["channels"]))
        table = listed()
        by_name = {n["name"]: n for n in table["nodes"]}
        assert set(by_name) == {"ups-sub", "ups-pub"} and by_name["ups-sub"]["connected"]
        channels = {c["name"]: c for c in table["channels"]}
        assert set(channels) == {"robot/speed", None}  # 0x1234 came without a name
        speed = channels["robot/speed"]
        assert speed["publishers"] == [by_name["ups-pub"]["node_id"]]
        assert speed["subscribers"] == [by_name["ups-sub"]["node_id"]]
        ls = Proc("ls", "--broker", address)
        code, out = ls.finish()
        assert code == 0
        row = next(line for line in out.splitlines() if "robot/speed" in line)
        assert row.split()[2:] == ["ups-pub", "ups-sub"]  # uid, name, publishers, subscribers
