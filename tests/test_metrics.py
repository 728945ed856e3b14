"""``--metrics HOST:PORT``: real daemons, real traffic through them, real HTTP scrapes read
with prometheus-client's own parser; docs/metrics.md lists exactly what the code serves.

The CAN daemons (``ups can-broker``, ``ups gateway``) are in test_metrics_can.py: their nodes
share a udp_multicast bus, in a private network namespace.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import queue
import socket
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from prometheus_client import ProcessCollector

from ups import Node
from ups import _metrics as ups_metrics
from ups._metrics import NODE, NODE_UNEXPOSED
from ups._tcpface import query_status
from ups.broker._metrics import TCP_ECB
from ups.jaus._metrics import JAUS
from ups.tools.console import CONSOLE

from .metrics_scrape import (
    VERSION,
    documented,
    metrics_url,
    rows_of_code,
    scrape,
    scrape_until,
    uncovered,
)
from .procs import ROOT, Proc, start_tcp_broker
from .test_tcp_processes import pub_proc, status, sub_proc

SUB_ID, JAUS_ID = 0x3E71, 0x3E72


def test_the_doc_lists_every_metric_the_code_serves_and_no_other() -> None:
    rows = documented()
    process = {f.samples[0].name: f for f in ProcessCollector(registry=None).collect()}
    for name, family in process.items():  # prometheus-client's own
        assert rows.pop(name, None) == (name, family.type, "", "prometheus-client",
                                        family.documentation), name  # fmt: skip
    code = rows_of_code()
    assert sorted(set(code) - set(rows)) == [], "in the code, not in docs/metrics.md"
    assert sorted(set(rows) - set(code)) == [], "in docs/metrics.md, not in the code"
    assert [rows[n] for n in code if rows[n] != code[n]] == [], "docs/metrics.md says otherwise"
    names = list(code)
    assert all(n.endswith("_total") == (code[n].kind == "counter") for n in names)


def test_the_broker_counts_the_nodes_that_come_and_go() -> None:
    broker, address = start_tcp_broker("--recovery", "0", "--metrics", "127.0.0.1:0")
    with broker:
        url = metrics_url(broker)
        empty = scrape(url)
        assert (
            empty.value("ups_tcp_ecb_nodes") == 0 and empty.value("ups_tcp_ecb_joined_total") == 0
        )
        assert empty.value("ups_build_info", daemon="broker", version=VERSION) == 1
        with sub_proc(address, "metrics/speed", node_id=SUB_ID, count=3) as sub:
            one = scrape(url)
            assert one.value("ups_tcp_ecb_nodes") == 1 and one.value("ups_tcp_ecb_channels") == 1
            assert one.value("ups_tcp_ecb_joined_total") == 1
            with pub_proc(address, "metrics/speed", "01", count=3, rate=50) as pub:
                assert pub.finish()[0] == 0
            code, out = sub.finish()
            assert code == 0 and len(out.splitlines()) == 3  # the events went by
        after = scrape_until(url, lambda s: s.get("ups_tcp_ecb_left_total") == 2)
        assert after.value("ups_tcp_ecb_joined_total") == 2
        assert after.value("ups_tcp_ecb_nodes") == 0 and after.value("ups_tcp_ecb_channels") == 0
        assert after.value("ups_tcp_ecb_links") == 0
        assert after.value("process_open_fds") > 0
        assert after.undocumented() == []
        stats = status(address)["stats"]  # what ups status shows: the same numbers
        assert uncovered(stats, [TCP_ECB]) == set()
        assert after.value("ups_tcp_ecb_joined_total") == stats["joined"] == 2
        assert scrape(url).value("ups_tcp_ecb_status_answers_total") >= 1  # that status


def test_only_metrics_is_served_there() -> None:
    broker, _ = start_tcp_broker("--recovery", "0", "--metrics", "127.0.0.1:0")
    with broker:
        url = metrics_url(broker)
        with pytest.raises(urllib.error.HTTPError) as error:
            urllib.request.urlopen(url.removesuffix("metrics") + "other", timeout=15)
        assert error.value.code == 404 and error.value.read() == b"UPS metrics are at /metrics\n"


def test_the_jaus_component_counts_an_ocu_driving_the_robot() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    mapping = str(ROOT / "examples" / "robot.jaus.toml")
    with broker, Proc(
        "sub", "robot/max-speed", "--broker", address, "--json", "--count", "1", "--timeout", "60"
    ) as wheels, Proc(
        "jaus", "--broker", address, "--map", mapping, "--listen", "127.0.0.1:0",
        "--node-id", hex(JAUS_ID), "--metrics", "127.0.0.1:0",
    ) as component:  # fmt: skip
        wheels.wait_for_line("subscribed to")
        line = component.wait_for_line(r"JAUS component 1\.1\.1 on 127\.0\.0\.1:\d+", timeout=60)
        target = line.split(" on ")[1].split()[0]
        url = metrics_url(component)
        before = scrape(url)
        assert before.value("ups_jaus_commands_total") == 0
        assert before.value("ups_node_broker_connected", network="tcp") == 1
        with Proc("jaus-ocu", "--target", target, "send", "SetWrenchEffort",
                  "propulsive_linear_x=25", "--control") as ocu:  # fmt: skip
            code, _ = ocu.finish(timeout=60)
            assert code == 0, "".join(ocu.stderr_lines)
        code, out = wheels.finish(timeout=60)
        assert code == 0 and json.loads(out)["data"] == "0032"  # 25 % -> 50 cm/s, on TCP
        after = scrape(url)
        assert after.value("ups_jaus_commands_total") == 1
        assert after.value("ups_jaus_control_granted_total") == 1
        assert after.value("ups_jaus_received_total") >= 3  # request control, resume, the effort
        assert after.value("ups_jaus_datagrams_total") >= after.value("ups_jaus_received_total")
        assert after.value("ups_jaus_sent_total") >= 1  # confirm control
        assert after.value("ups_jaus_clients") == 1
        assert after.value("ups_node_published_total", network="tcp") == 1
        assert after.value("ups_node_sent_total", network="tcp") == 1  # to the one subscriber
        assert after.get("ups_can_rx_frames_total") == -1  # not on CAN: no CAN link
        assert after.undocumented() == []
        node = next(n for n in status(address)["nodes"] if n["name"] == "ups-jaus")
        info = asyncio.run(query_status(node["address"], timeout=10))
        assert uncovered(info["jaus"]["stats"], [JAUS]) == set()
        assert uncovered(info["stats"], [NODE], NODE_UNEXPOSED) == set()


def test_the_console_counts_the_events_it_follows() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        Proc("pub", "metrics/seen", "2a", "--broker", address, "--count", "100000",
             "--rate", "50"),
        Proc("console", "--listen", "127.0.0.1:0", "--broker", address,
             "--metrics", "127.0.0.1:0") as console,
    ):  # fmt: skip
        url = metrics_url(console)
        seen = scrape_until(url, lambda s: s.get("ups_console_events_total") >= 10)
        assert seen.value("ups_node_received_total", network="tcp") >= 10  # its node got them
        assert seen.value("ups_console_channels") == 1
        assert seen.value("ups_console_nodes") == 1  # the publisher (not the console itself)
        assert seen.value("ups_console_pages") == 0
        assert seen.value("ups_build_info", daemon="console", version=VERSION) == 1
        assert seen.get("ups_console_bus_load") == -1  # on TCP/IP: no bus
        assert seen.undocumented() == []
        page = console.wait_for_line(r"console on http://").split("console on ")[1].strip()
        with urllib.request.urlopen(f"{page}/snapshot", timeout=15) as response:
            snapshot = json.load(response)
        assert uncovered(snapshot["counters"], [CONSOLE]) == set()


async def test_counters_are_read_on_the_event_loop_and_a_held_up_loop_is_a_503(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A scrape never reads the counters from its own thread (it could see a change half
    made): the loop reads them. While the loop cannot, the scrape gives up: 503."""
    monkeypatch.setattr(ups_metrics, "SCRAPE_TIMEOUT", 0.5)
    readers: list[threading.Thread] = []
    counters = {"published": 7}

    def read() -> ups_metrics.Reading:
        readers.append(threading.current_thread())
        return [(NODE, counters, {"network": "tcp"})]

    async with ups_metrics.serving_metrics("127.0.0.1:0", "test", read) as server:
        assert server is not None
        found = await asyncio.to_thread(scrape, server.url)
        assert found.value("ups_node_published_total", network="tcp") == 7
        assert readers == [threading.current_thread()]  # the loop's thread, not the server's
        answered: queue.Queue[int] = queue.Queue()

        def scrape_status() -> None:
            try:
                urllib.request.urlopen(server.url, timeout=15)
                answered.put(200)
            except urllib.error.HTTPError as exc:
                answered.put(exc.code)

        threading.Thread(target=scrape_status, daemon=True).start()
        assert answered.get(timeout=15) == 503  # the loop is held up right here, waiting
        counters["published"] = 8
        found = await asyncio.to_thread(scrape, server.url)  # the loop free again: answered
        assert found.value("ups_node_published_total", network="tcp") == 8


def _threads_in(function: str) -> int:
    """How many threads are in a call of ``function`` (a name) now."""
    found = 0
    for frame in sys._current_frames().values():
        while frame is not None and frame.f_code.co_name != function:
            frame = frame.f_back  # type: ignore[assignment]
        found += frame is not None
    return found


async def test_scrapes_that_wait_together_share_one_read_of_the_counters() -> None:
    """Scrapes that come while the loop is busy cost it one read between them, not one each."""
    reads = 0

    def read() -> ups_metrics.Reading:
        nonlocal reads
        reads += 1
        return [(NODE, {"published": 7}, {"network": "tcp"})]

    async with ups_metrics.serving_metrics("127.0.0.1:0", "test", read) as server:
        assert server is not None
        with concurrent.futures.ThreadPoolExecutor(4) as scrapers:
            waiting = [scrapers.submit(scrape, server.url) for _ in range(4)]
            deadline = time.monotonic() + 15
            while _threads_in("_on_loop") < 4:  # the loop is held here until all four wait
                assert time.monotonic() < deadline
            found = await asyncio.gather(*map(asyncio.wrap_future, waiting))
        assert [f.value("ups_node_published_total", network="tcp") for f in found] == [7] * 4
        assert reads == 1
        after = await asyncio.to_thread(scrape, server.url)
        assert after.value("ups_metrics_answers_total") == 4


async def test_what_is_not_a_scrape_is_answered_so_and_counted() -> None:
    async with ups_metrics.serving_metrics("127.0.0.1:0", "test", lambda: []) as server:
        assert server is not None
        answers = []
        for request in (b"hello\r\n\r\n", b"GET /metrics HTTP/1.1\r\nX: " + b"a" * 9000):
            reader, writer = await asyncio.open_connection(server.host, server.port)
            writer.write(request)
            answers.append((await reader.read()).split(b"\r\n", 1)[0])
            writer.close()
        assert answers == [b"HTTP/1.1 400 Bad Request", b"HTTP/1.1 431 Request Header Fields "
                           b"Too Large"]  # fmt: skip
        post = urllib.request.Request(server.url, method="POST")
        with pytest.raises(urllib.error.HTTPError) as error:
            await asyncio.to_thread(urllib.request.urlopen, post, timeout=15)
        assert error.value.code == 405
        found = await asyncio.to_thread(scrape, server.url)
        assert found.value("ups_metrics_bad_requests_total") == 2
        assert found.value("ups_metrics_answers_total") == 1  # the 405


async def test_a_zenoh_nodes_counters_are_all_served(zenoh_router: str) -> None:
    """The process tests run nodes on TCP/IP and CAN; a Zenoh node's counters, here, through
    the same table and reading as a daemon's."""
    async with Node(zenoh=zenoh_router, node_id=0x3E73) as node:
        await node.publish("metrics/zenoh", b"1")
        stats = node.stats()
        assert uncovered(stats, [NODE], NODE_UNEXPOSED) == set()
        found = {s.name: s for s in ups_metrics.samples([(NODE, stats, {"network": "zenoh"})])}
        assert found["ups_node_sent_total"].value == 1
        assert found["ups_node_router_connected"].labels == (("network", "zenoh"),)
        assert "ups_node_peers" not in found  # a TCP node's: not served for this one


@pytest.mark.parametrize(
    ("metrics", "says"),
    [
        ("nope", "ups broker: --metrics expects HOST:PORT (e.g. 127.0.0.1:9464), got 'nope'"),
        (
            "127.0.0.1:http",
            "ups broker: --metrics expects HOST:PORT (e.g. 127.0.0.1:9464), got '127.0.0.1:http'",
        ),
        ("no.such.host.invalid:9464", "ups broker: cannot serve metrics on no.such.host.invalid"),
    ],
)
def test_a_bad_metrics_address_is_one_line_and_exit_2(metrics: str, says: str) -> None:
    proc = Proc("broker", "--listen", "127.0.0.1:0", "--metrics", metrics)
    code, _ = proc.finish()
    assert code == 2 and len(proc.stderr_lines) == 1, proc.stderr_lines
    assert proc.stderr_lines[0].startswith(says)


def test_a_metrics_port_in_use_is_one_line_and_exit_2() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = Proc("broker", "--listen", "127.0.0.1:0", "--metrics", f"127.0.0.1:{port}")
        code, _ = proc.finish()
    assert code == 2 and proc.stderr_lines == [
        f"ups broker: cannot serve metrics on 127.0.0.1:{port}: Address already in use\n"
    ]


@pytest.mark.parametrize(
    "command",
    [
        ("broker", "--listen", "127.0.0.1:0"),
        ("can-broker", "--can", "virtual:metrics-missing", "--db", "DB"),
        ("gateway", "--can", "virtual:metrics-missing", "--broker", "127.0.0.1:1", "--db", "DB"),
        ("jaus", "--broker", "127.0.0.1:1", "--map", str(ROOT / "examples" / "robot.jaus.toml")),
        ("console", "--listen", "127.0.0.1:0", "--broker", "127.0.0.1:1"),
    ],
)
def test_without_prometheus_client_metrics_say_what_to_install(
    command: tuple[str, ...], tmp_path: Path
) -> None:
    (tmp_path / "prometheus_client.py").write_text("raise ImportError('not installed')\n")
    args = [str(tmp_path / "ecb.db") if a == "DB" else a for a in command]
    proc = Proc(*args, "--metrics", "127.0.0.1:0", env={"PYTHONPATH": f"{tmp_path}:{ROOT}"})
    code, _ = proc.finish(timeout=60)
    assert code == 2 and proc.stderr_lines == [
        f"ups {command[0]}: --metrics needs prometheus-client: pip install 'ups-pubsub[metrics]'\n"
    ]
