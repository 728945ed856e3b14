"""UPS on Zenoh as separate processes: ``ups zenoh-router``, ``ups gateway --zenoh``, ``ups pub``
and ``ups sub`` on CAN (udp_multicast) and on Zenoh, a plain Zenoh subscriber with no UPS code,
and a raw CAN listener checking what reaches each bus.

One site on loopback inside the private namespace; then two "sites", network namespaces joined
by a veth pair, each with its router, its gateway and its own CAN bus, the routers linked.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from ups import name_to_uid

from .procs import ROOT, Proc, private_multicast_bus
from .test_tcp_processes import wait_until

#: a Zenoh subscriber with no UPS code: one JSON line per sample (key, payload in hex)
PLAIN_SUB = """
import json, os, sys, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
session = zenoh.open(conf)
def show(sample):
    print(json.dumps({"key": str(sample.key_expr), "data": sample.payload.to_bytes().hex()}),
          flush=True)
sub = session.declare_subscriber(sys.argv[2], show)
print("ready", flush=True)
sys.stdin.read()  # until the test closes our input
sub.undeclare()
session.close()
sys.stdout.flush()
os._exit(0)
"""

#: every non-management frame on a bus, one JSON line each, until stdin closes
RAW_LISTENER = """
import json, sys, threading
from ups._canlink import open_bus
from ups import _canproto as p
bus = open_bus(sys.argv[1])
done = threading.Event()
threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
print("ready", flush=True)
while not done.is_set():
    frame = bus.recv(0.1)
    if frame is not None and not p.is_management(frame.arbitration_id):
        print(json.dumps({"id": frame.arbitration_id, "data": frame.data.hex()}), flush=True)
bus.shutdown()
"""


class Script:
    """``python -c CODE ARGS`` (under ``prefix``), its stdout lines collected; stops when its
    stdin closes."""

    def __init__(self, code: str, *args: str, prefix: tuple[str, ...] = ()) -> None:
        self.popen = subprocess.Popen(
            [*prefix, sys.executable, "-c", code, *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        assert self.popen.stdout is not None
        ready = self.popen.stdout.readline()
        assert ready.strip() == "ready", f"the script did not start: {ready!r}"

    def lines(self) -> list[dict[str, Any]]:
        """Stop it; every line it printed."""
        assert self.popen.stdin is not None and self.popen.stdout is not None
        self.popen.stdin.close()
        out = self.popen.stdout.read()
        self.popen.wait(timeout=10)
        return [json.loads(line) for line in out.splitlines()]

    def __enter__(self) -> Script:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()


def start_router(listen: str, *more: str, prefix: tuple[str, ...] = ()) -> Proc:
    router = Proc("zenoh-router", "--listen", listen, *more, prefix=prefix)
    try:
        router.wait_for_line("Zenoh router .* on")
    except BaseException:
        router.stop()
        raise
    return router


def start_gateway(
    bus: str, endpoint: str, db: Path, node_id: int, prefix: tuple[str, ...] = ()
) -> Proc:
    gw = Proc(
        "gateway", "--can", bus, "--zenoh", endpoint, "--db", str(db), "--node-id", hex(node_id),
        "--recovery", "0.2", prefix=prefix,
    )  # fmt: skip
    try:
        gw.wait_for_line(r"gateway .* and the Zenoh router", timeout=60)
    except BaseException:
        gw.stop()
        raise
    return gw


def zenoh_status(endpoint: str, prefix: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """``ups status --zenoh``: every UPS node and gateway on the network."""
    out = subprocess.run(
        [*prefix, sys.executable, "-m", "upscli", "status", "--zenoh", endpoint, "--json"],
        capture_output=True, text=True, check=True, cwd=ROOT, timeout=30,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    ).stdout  # fmt: skip
    return list(json.loads(out))


def gateway_info(endpoint: str, node_id: int, prefix: tuple[str, ...] = ()) -> dict[str, Any]:
    for entry in zenoh_status(endpoint, prefix):
        if entry["node_id"] == f"0x{node_id:016x}" and "gateway" in entry:
            return dict(entry["gateway"])
    return {}


def forwarding(
    endpoint: str, node_id: int, channel: str, to: str, prefix: tuple[str, ...] = ()
) -> bool:
    uid = f"0x{name_to_uid(channel):016x}"
    return uid in gateway_info(endpoint, node_id, prefix).get(f"channels_to_{to}", [])


def events(proc: Proc) -> list[dict[str, Any]]:
    return [json.loads(line) for line in proc.stdout_lines]


@pytest.mark.netns
@pytest.mark.timeout(180)
def test_one_site_can_and_zenoh_both_ways(tmp_path: Path) -> None:
    bus = private_multicast_bus()
    endpoint = "tcp/127.0.0.1:17447"
    with (
        start_router(endpoint),
        start_gateway(bus, endpoint, tmp_path / "gw.db", 0x6A7E),
        Script(RAW_LISTENER, bus) as wire,
    ):
        # CAN -> a plain Zenoh subscriber (no UPS code) and a UPS one, priority kept
        with (
            Script(PLAIN_SUB, endpoint, "ups/**") as plain,
            Proc("sub", "speed", "--zenoh", endpoint, "--json", "--count", "3", "--timeout",
                 "60") as zsub,
        ):  # fmt: skip
            zsub.wait_for_line("subscribed to")
            with Proc("pub", "speed", "0102", "--can", bus, "--count", "200", "--rate", "20",
                      "--priority", "0x30", "--node-id", "0xC1"):  # fmt: skip
                assert zsub.finish(timeout=60)[0] == 0
            got = events(zsub)
            assert {(e["data"], e["priority"], e["source"]) for e in got} == {
                ("0102", 0x30, f"0x{0x6A7E:016x}")
            }
            seen = plain.lines()
            assert seen and {s["data"] for s in seen} == {"0102"}
            assert {s["key"] for s in seen} == {f"ups/{name_to_uid('speed'):016x}"}
        # Zenoh -> CAN, for a channel a CAN node subscribes to, priority kept
        with Proc("sub", "cmd", "--can", bus, "--json", "--count", "2", "--timeout", "60",
                  "--node-id", "0xC2") as csub:  # fmt: skip
            csub.wait_for_line("subscribed to")
            wait_until(lambda: forwarding(endpoint, 0x6A7E, "cmd", "can"), timeout=30)
            with Proc("pub", "cmd", "09", "--zenoh", endpoint, "--count", "2", "--rate", "20",
                      "--priority", "0x40") as zpub:  # fmt: skip
                assert zpub.finish(timeout=60)[0] == 0
            assert csub.finish(timeout=60)[0] == 0
            assert [(e["data"], e["priority"]) for e in events(csub)] == [("09", 0x40)] * 2
        # a Zenoh channel no CAN node subscribes to: nothing on the bus
        with Proc("pub", "lonely", "77", "--zenoh", endpoint, "--count", "5", "--rate", "50") as p:
            assert p.finish(timeout=60)[0] == 0
        info = gateway_info(endpoint, 0x6A7E)
        assert info["to_can"] == 2 and info["to_zenoh"] >= 3 and info["can_dropped"] == 0
        frames = wire.lines()
        assert "77" not in {f["data"] for f in frames}
        assert [f["data"] for f in frames].count("09") == 2


# --- two sites ------------------------------------------------------------------------------

SITE_A, SITE_B = "10.78.0.1", "10.78.0.2"


@contextlib.contextmanager
def two_sites() -> Iterator[tuple[tuple[str, ...], tuple[str, ...]]]:
    """Two network namespaces joined by a veth pair, each with loopback multicast for its own
    udp_multicast CAN bus; yields the command prefix that runs a process in each."""
    if os.geteuid() != 0:
        reason = "needs root: ip netns add and a veth pair"
        if os.environ.get("UPS_REQUIRE_NETNS") == "1":
            pytest.fail(reason)
        pytest.skip(reason)
    private_multicast_bus()  # only inside the private namespace, never beside a real network
    tag = str(os.getpid() % 100000)
    names = (f"ups-zs-{tag}-a", f"ups-zs-{tag}-b")
    devs = (f"zsa{tag}", f"zsb{tag}")
    made: list[str] = []
    try:
        for ns in names:
            subprocess.run(["ip", "netns", "add", ns], check=True)
            made.append(ns)
        run = [
            ["ip", "link", "add", devs[0], "type", "veth", "peer", "name", devs[1]],
        ]
        for ns, dev, addr in zip(names, devs, (SITE_A, SITE_B), strict=True):
            run += [
                ["ip", "link", "set", dev, "netns", ns],
                ["ip", "-n", ns, "addr", "add", f"{addr}/24", "dev", dev],
                ["ip", "-n", ns, "link", "set", dev, "up"],
                ["ip", "-n", ns, "link", "set", "lo", "up", "multicast", "on"],
                ["ip", "-n", ns, "route", "add", "224.0.0.0/4", "dev", "lo"],
            ]
        for cmd in run:
            subprocess.run(cmd, check=True)
        yield tuple(("ip", "netns", "exec", ns) for ns in names)  # type: ignore[misc]
    finally:
        for ns in made:  # deleting a namespace deletes its end of the pair, and so both ends
            subprocess.run(["ip", "netns", "del", ns], check=False)


@pytest.mark.netns
@pytest.mark.timeout(300)
def test_two_sites_wan_of_cans_through_linked_routers(tmp_path: Path) -> None:
    bus = private_multicast_bus()  # the same spec names a different bus in each namespace
    with two_sites() as (in_a, in_b):
        end_a, end_b = f"tcp/{SITE_A}:7447", f"tcp/{SITE_B}:7447"
        gw_a_id, gw_b_id = 0x6A01, 0x6B01
        with (
            start_router(end_a, prefix=in_a),
            start_router(end_b, "--connect", end_a, prefix=in_b) as router_b,
            start_gateway(bus, end_a, tmp_path / "a.db", gw_a_id, prefix=in_a),
            start_gateway(bus, end_b, tmp_path / "b.db", gw_b_id, prefix=in_b),
            Script(RAW_LISTENER, bus, prefix=in_b) as wire_b,
        ):
            # CAN A -> CAN B
            with Proc("sub", "site/speed", "--can", bus, "--json", "--count", "3", "--timeout",
                      "60", "--node-id", "0xB1", prefix=in_b) as sub_b:  # fmt: skip
                sub_b.wait_for_line("subscribed to")
                wait_until(lambda: forwarding(end_b, gw_b_id, "site/speed", "can", in_b), 30)
                with Proc("pub", "site/speed", "0a0b", "--can", bus, "--count", "200",
                          "--rate", "20", "--priority", "0x30", "--node-id", "0xA1",
                          prefix=in_a):  # fmt: skip
                    assert sub_b.finish(timeout=60)[0] == 0
                assert {(e["data"], e["priority"]) for e in events(sub_b)} == {("0a0b", 0x30)}
            # a host on Zenoh only (site B) <-> CAN A, both ways
            with Proc("sub", "site/odom", "--zenoh", end_b, "--json", "--count", "3",
                      "--timeout", "60", prefix=in_b) as zsub:  # fmt: skip
                zsub.wait_for_line("subscribed to")
                with Proc("pub", "site/odom", "0c", "--can", bus, "--count", "200", "--rate",
                          "20", "--node-id", "0xA2", prefix=in_a):  # fmt: skip
                    assert zsub.finish(timeout=60)[0] == 0
                assert {e["source"] for e in events(zsub)} == {f"0x{gw_a_id:016x}"}
            with Proc("sub", "site/cmd", "--can", bus, "--json", "--count", "2", "--timeout",
                      "60", "--node-id", "0xA3", prefix=in_a) as sub_a:  # fmt: skip
                sub_a.wait_for_line("subscribed to")
                wait_until(lambda: forwarding(end_b, gw_a_id, "site/cmd", "can", in_b), 30)
                with Proc("pub", "site/cmd", "0d", "--zenoh", end_b, "--count", "2", "--rate",
                          "20", prefix=in_b) as zpub:  # fmt: skip
                    assert zpub.finish(timeout=60)[0] == 0
                assert sub_a.finish(timeout=60)[0] == 0
            # bus B carried only the channel a node on it subscribes to
            seen_b = {f["data"] for f in wire_b.lines()}
            assert "0a0b" in seen_b and not seen_b & {"0c", "0d"}

            # router B killed and restarted mid-stream: every event gateway A sent either
            # reaches CAN B or is counted lost by gateway B
            def totals() -> tuple[int, int] | None:
                """(events gateway A sent to Zenoh, events gateway B counted lost), once both
                answer (after a restart, their sessions take a moment to find the router)."""
                sent = gateway_info(end_b, gw_a_id, in_b).get("to_zenoh")
                lost = gateway_info(end_b, gw_b_id, in_b).get("zenoh_lost")
                return None if sent is None or lost is None else (sent, lost)

            with Proc("sub", "site/stream", "--can", bus, "--json", "--node-id", "0xB2",
                      prefix=in_b) as stream_b:  # fmt: skip
                stream_b.wait_for_line("subscribed to")
                wait_until(lambda: forwarding(end_b, gw_b_id, "site/stream", "can", in_b), 30)
                before = totals()
                assert before is not None
                sent_before, lost_before = before
                pub = Proc("pub", "site/stream", "ee", "--can", bus, "--count", "250", "--rate",
                           "50", "--node-id", "0xA4", prefix=in_a)  # fmt: skip
                with pub:
                    wait_until(lambda: len(stream_b.stdout_lines) >= 20, timeout=30)
                    router_b.kill()
                    with start_router(end_b, "--connect", end_a, prefix=in_b):
                        assert pub.finish(timeout=60)[0] == 0
                        settled: list[tuple[int, int] | None] = []

                        def quiet() -> bool:  # the same totals twice: nothing in flight
                            settled.append(totals())
                            return settled[-1] is not None and settled[-2:] == settled[-1:] * 2

                        wait_until(quiet, timeout=30)
                        last = settled[-1]
                        assert last is not None
                        sent, lost = last[0] - sent_before, last[1] - lost_before

                        stream_b.stop()
                        received = len(stream_b.stdout_lines)
                        assert lost > 0  # the restart did cost events, and they were counted
                        assert received + lost == sent
                        assert received > 20  # and the stream resumed after it
