"""``--metrics`` of the CAN daemons, ``ups can-broker`` and ``ups gateway``, with real nodes
(``ups pub``, ``ups sub``) on a udp_multicast bus in a private network namespace
(scripts/netns-run), and real scrapes."""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path

import pytest

from ups._metrics import NODE, NODE_UNEXPOSED
from ups._tcpface import query_status
from ups.broker._metrics import CAN_ECB, CAN_ECB_UNEXPOSED, STATUS_PORT
from ups.gateway._metrics import GATEWAY_UNEXPOSED, gateway_table

from .metrics_scrape import VERSION, metrics_url, scrape, scrape_until, uncovered
from .procs import Proc, private_multicast_bus, start_tcp_broker

pytestmark = [pytest.mark.netns, pytest.mark.timeout(240)]


def address_in(proc: Proc, pattern: str) -> str:
    found = re.search(pattern, proc.wait_for_line(pattern, timeout=60))
    assert found is not None
    return found.group(1)


def test_the_can_broker_counts_joins_the_census_and_bindings(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    with Proc(
        "can-broker", "--can", bus, "--db", f"{tmp_path}/ecb.db", "--recovery", "0.2",
        "--status", "127.0.0.1:0", "--metrics", "127.0.0.1:0",
    ) as ecb:  # fmt: skip
        status_address = address_in(ecb, r"status on (127\.0\.0\.1:\d+)")
        url = metrics_url(ecb)
        ecb.wait_for_line("CAN-ECB on")
        before = scrape(url)
        assert before.value("ups_can_ecb_joined_total") == 0
        assert before.value("ups_can_ecb_txnodes") == 0
        assert before.value("ups_build_info", daemon="can-broker", version=VERSION) == 1
        with Proc(
            "sub", "metrics/can", "--can", bus, "--json", "--count", "3", "--timeout", "60",
            "--node-id", "0xC1",
        ) as sub:  # fmt: skip
            sub.wait_for_line("subscribed to")
            with Proc(
                "pub", "metrics/can", "0102", "--can", bus, "--count", "100", "--rate", "20",
                "--node-id", "0xC2",
            ):  # fmt: skip
                code, out = sub.finish(timeout=60)
        assert code == 0 and [json.loads(e)["data"] for e in out.splitlines()] == ["0102"] * 3
        after = scrape(url)
        assert after.value("ups_can_ecb_joined_total") == 2  # the subscriber and the publisher
        assert after.value("ups_can_ecb_txnodes") == 2
        assert after.value("ups_can_ecb_census_knocks_total") >= 2
        assert after.value("ups_can_ecb_census_censuses_total") >= 1
        assert after.value("ups_can_ecb_census_queries_total") >= 1
        assert after.value("ups_can_ecb_census_stages_total") >= 16  # 16 nibbles of an id
        assert after.value("ups_can_ecb_bound_total") == 1 and after.value("ups_can_ecb_etags") == 1
        assert after.value("ups_can_ecb_requests_total") >= 2  # a SUB_BIND, a PUB_BIND
        assert after.value("ups_can_ecb_healthy") == 1 and after.value("ups_can_ecb_standby") == 0
        assert after.value("ups_can_rx_frames_total") >= 3  # it hears the events too
        assert after.value("ups_can_tx_frames_total") >= 2  # its Assigns and Binds
        assert after.value("ups_can_ecb_status_answers_total") == 0
        assert after.undocumented() == []
        info = asyncio.run(query_status(status_address, timeout=10))
        assert uncovered(info["stats"], [CAN_ECB, STATUS_PORT], CAN_ECB_UNEXPOSED) == set()
        assert scrape(url).value("ups_can_ecb_status_answers_total") == 1


def test_the_gateway_counts_what_it_forwards_each_way(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc(
        "gateway", "--can", bus, "--broker", address, "--db", str(tmp_path / "gw.db"),
        "--recovery", "0.2", "--metrics", "127.0.0.1:0",
    ) as gw:  # fmt: skip
        gw_address = address_in(gw, r"gateway .* listening on (\S+:\d+)")
        url = metrics_url(gw)
        # CAN publisher -> TCP subscriber
        with Proc(
            "sub", "speed", "--broker", address, "--json", "--count", "3", "--timeout", "60"
        ) as tcp_sub:
            tcp_sub.wait_for_line("subscribed to")
            with Proc(
                "pub", "speed", "0102", "--can", bus, "--count", "100", "--rate", "20",
                "--node-id", "0xC1",
            ):  # fmt: skip
                code, _ = tcp_sub.finish(timeout=60)
                assert code == 0
                up = scrape(url)
        assert up.value("ups_gateway_forwarded_total", direction="to_ip") >= 3
        assert up.value("ups_node_sent_total", network="tcp") >= 3  # to the TCP subscriber
        assert up.value("ups_gateway_forwarded_total", direction="to_can") == 0
        # TCP publisher -> CAN subscriber
        with Proc(
            "sub", "cmd", "--can", bus, "--json", "--count", "2", "--timeout", "60",
            "--node-id", "0xC2",
        ) as can_sub:  # fmt: skip
            can_sub.wait_for_line("subscribed to")
            scrape_until(url, lambda s: s.get("ups_gateway_forwarding_channels",
                                              direction="to_can") == 1)  # fmt: skip
            with Proc(
                "pub", "cmd", "09", "--broker", address, "--count", "2", "--rate", "20"
            ) as pub:
                assert pub.finish(timeout=60)[0] == 0
            code, out = can_sub.finish(timeout=60)
            assert code == 0 and [json.loads(e)["data"] for e in out.splitlines()] == ["09"] * 2
        down = scrape(url)
        assert down.value("ups_gateway_forwarded_total", direction="to_can") == 2
        assert down.value("ups_node_received_total", network="tcp") == 2
        assert down.value("ups_node_sent_total", network="can") == 2
        assert down.value("ups_gateway_can_dropped_total") == 0
        assert down.value("ups_gateway_can_queued") == 0
        assert down.value("ups_can_ecb_joined_total") == 3  # the gateway's node and two others
        assert down.value("ups_node_txnode", network="can") >= 0
        assert down.value("ups_can_tx_frames_total") >= 2
        assert down.value("ups_build_info", daemon="gateway", version=VERSION) == 1
        assert down.undocumented() == []
        info = asyncio.run(query_status(gw_address, timeout=10))
        unexposed = {k.replace("SIDE", "tcp"): v for k, v in GATEWAY_UNEXPOSED.items()}
        assert uncovered(info["gateway"], [gateway_table("tcp")], unexposed) == set()
        assert uncovered(info["gateway"]["can_node"], [NODE], NODE_UNEXPOSED) == set()
        assert uncovered(info["gateway"]["can_ecb"], [CAN_ECB], CAN_ECB_UNEXPOSED) == set()
        assert uncovered(info["stats"], [NODE], NODE_UNEXPOSED) == set()
