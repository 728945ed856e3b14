"""``ups broker``, ``ups sub --broker`` and ``ups pub --broker`` as separate processes on loopback.

Faults are real: the TCP-ECB is killed with SIGKILL mid-stream and restarted on its port, a
subscriber is killed, another is frozen with SIGSTOP, and bad bytes are thrown at the daemons.
"""

from __future__ import annotations

import asyncio
import json
import re
import socket
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ups import _tcpwire as w
from ups import name_to_uid
from ups._tcpface import query_status

from .procs import Proc, start_tcp_broker

PUB_ID = 0x7B1
SUB_ID = 0x5B1


def status(address: str) -> dict:  # type: ignore[type-arg]
    return asyncio.run(query_status(address, timeout=5))


def wait_until(predicate, timeout: float = 10.0) -> None:  # type: ignore[no-untyped-def]
    """Poll ``predicate`` (it asks a daemon over TCP) until true; fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        time.sleep(0.05)


def subscribers_of(address: str, channel: str) -> list[str]:
    uid = f"0x{name_to_uid(channel):016x}"
    for entry in status(address)["channels"]:
        if entry["uid"] == uid:
            return list(entry["subscribers"])  # msgpack arrays arrive as tuples
    return []


def sub_proc(
    address: str,
    *channels: str,
    node_id: int,
    count: int,
    json_out: bool = True,
    stdout: Path | None = None,
) -> Proc:
    args = ["sub", *channels, "--broker", address, "--node-id", hex(node_id)]
    args += ["--count", str(count), "--timeout", "60"] + (["--json"] if json_out else [])
    proc = Proc(*args, stdout=stdout)
    proc.wait_for_line("subscribed to")
    return proc


def pub_proc(address: str, channel: str, data: str, *, count: int, rate: float, **kw: str) -> Proc:
    args = ["pub", channel, data, "--broker", address, "--node-id", hex(PUB_ID)]
    args += ["--count", str(count), "--rate", str(rate)]
    for key, value in kw.items():
        args += [f"--{key}", value]
    return Proc(*args)


def test_sub_pub_and_unsubscribe_across_processes() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, sub_proc(address, "speed", "0x1234", node_id=SUB_ID, count=4) as sub:
        assert subscribers_of(address, "speed") == [f"0x{SUB_ID:016x}"]
        with pub_proc(address, "speed", "0102", count=3, rate=100, priority="0x20") as pub:
            assert pub.finish()[0] == 0
        with pub_proc(address, "0x1234", "ff", count=1, rate=100) as pub:
            assert pub.finish()[0] == 0
        code, out = sub.finish()
        assert code == 0
        events = [json.loads(line) for line in out.splitlines()]
        assert [(e["channel"], e["data"], e["priority"]) for e in events] == [
            ("speed", "0102", 0x20),
            ("speed", "0102", 0x20),
            ("speed", "0102", 0x20),
            (None, "ff", 0x80),
        ]
        assert {e["source"] for e in events} == {f"0x{PUB_ID:016x}"}
        assert events[3]["uid"] == "0x0000000000001234"
        # The subscriber withdrew as it exited: it is in no list, and the ECB forgot it.
        assert subscribers_of(address, "speed") == []
        assert not status(address)["nodes"]


def test_fan_out_to_several_subscriber_processes() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    subs = [sub_proc(address, "fan", node_id=SUB_ID + i, count=5) for i in range(3)]
    with broker:
        try:
            with pub_proc(address, "fan", "abcd", count=5, rate=200) as pub:
                assert pub.finish()[0] == 0
            for sub in subs:
                code, out = sub.finish()
                assert code == 0
                assert [json.loads(line)["data"] for line in out.splitlines()] == ["abcd"] * 5
        finally:
            for sub in subs:
                sub.stop()


def test_ecb_killed_mid_stream_then_restarted() -> None:
    first, address = start_tcp_broker("--recovery", "1.5")
    port = int(address.rpartition(":")[2])
    count = 600
    with (
        first,
        sub_proc(address, "flow", node_id=SUB_ID, count=count) as old_sub,
        pub_proc(address, "flow", "01", count=count, rate=100) as pub,
    ):
        wait_until(lambda: len(old_sub.stdout_lines) >= 20)
        first.kill()  # SIGKILL: no goodbye to anyone
        pub.wait_for_line("lost the TCP-ECB")
        during = len(old_sub.stdout_lines)
        wait_until(lambda: len(old_sub.stdout_lines) >= during + 30)  # still flowing
        second, address = start_tcp_broker("--recovery", "1.5", port=port)
        # A subscriber that comes after the restart gets the events from then on. It stays to
        # the end: one that left mid-stream could miss an event sent before its publisher
        # heard that it left, which the publisher counts as dropped (the wider that moment,
        # the busier the machine).
        with second, sub_proc(address, "flow", node_id=SUB_ID + 1, count=count) as new_sub:
            wait_until(lambda: len(new_sub.stdout_lines) >= 5)
            assert pub.finish(timeout=30)[0] == 0, "".join(pub.stderr_lines)  # nothing dropped
            code = new_sub.stop()  # SIGTERM: it says what it lost (nothing), exit 0
            assert code == 0, f"the subscriber that came after the restart: {new_sub.stderr_lines}"
            assert 5 <= len(new_sub.stdout_lines) < count
            code, out = old_sub.finish(timeout=30)
            assert code == 0
            assert len(out.splitlines()) == count  # not one event lost
            assert not status(address)["nodes"]  # every node left cleanly


def test_a_killed_subscriber_leaves_the_lists() -> None:
    broker, address = start_tcp_broker("--recovery", "0", "--liveness", "1")
    with (
        broker,
        sub_proc(address, "x", node_id=SUB_ID, count=1000) as sub,
        pub_proc(address, "x", "00", count=1000, rate=50) as pub,
    ):
        wait_until(lambda: len(sub.stdout_lines) >= 3)
        nodes = {n["node_id"]: n for n in status(address)["nodes"]}
        pub_address = nodes[f"0x{PUB_ID:016x}"]["address"]
        assert [p["node_id"] for p in status(pub_address)["peers"]] == [f"0x{SUB_ID:016x}"]
        sub.kill()
        wait_until(lambda: subscribers_of(address, "x") == [], timeout=5)
        wait_until(lambda: not status(pub_address)["peers"], timeout=5)
        assert f"0x{SUB_ID:016x}" not in {n["node_id"] for n in status(address)["nodes"]}
        pub.stop()


@pytest.mark.timeout(240)  # 40 MB printed by the live subscriber: a minute on a busy machine
def test_a_stalled_subscriber_does_not_slow_the_others(tmp_path: Path) -> None:
    """A frozen subscriber fills the kernel's buffers, then its queue; its drops are counted."""
    broker, address = start_tcp_broker("--recovery", "0")
    count = 20_000  # 1000 bytes each: far more than the kernel buffers of the frozen link
    data = "ab" * 1000
    # The live subscriber prints 40 MB: into a file, so that it never waits for this process
    # to read a pipe (ups sub waits on its output with its event loop; after the TCP-ECB's
    # liveness, 3 s, the ECB takes it for dead).
    with (
        broker,
        sub_proc(
            address,
            "bulk",
            node_id=SUB_ID,
            count=count,
            json_out=False,
            stdout=tmp_path / "fast.out",
        ) as fast,  # fmt: skip
        sub_proc(address, "bulk", node_id=SUB_ID + 1, count=count, json_out=False) as stalled,
    ):
        stalled.pause()
        with pub_proc(address, "bulk", data, count=count, rate=4000) as pub:
            line = pub.wait_for_line(r"dropped \d+ events for subscriber 00000000000005b2")
            assert "queue of 1024 is full (drop_oldest)" in line
            code, _ = fast.finish(timeout=180)
            assert code == 0  # every event reached the live subscriber
            assert len(fast.stdout_lines) == count
            code, _ = pub.finish(timeout=30)
            assert code == 1, "".join(pub.stderr_lines)
            assert any("events were dropped" in line for line in pub.stderr_lines)
            assert not any("5b1 at" in line for line in pub.stderr_lines)  # none for the fast one
        stalled.resume()


def _throw(address: str, data: bytes) -> None:
    host, _, port = address.rpartition(":")
    with socket.create_connection((host, int(port)), timeout=5) as s:
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)
        s.settimeout(5)
        while s.recv(1 << 16):  # the daemon answers or closes; either way it read our bytes
            pass


def test_bad_bytes_leave_the_daemons_serving() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, sub_proc(address, "ok", node_id=SUB_ID, count=1) as sub:
        nodes = status(address)["nodes"]
        sub_address = nodes[0]["address"]
        oversized = (w.VERSION << 24 | w.MAX_BODY).to_bytes(4, "big") + bytes(100)
        wrong_version = (9 << 24 | 1).to_bytes(4, "big") + b"\x90"
        not_msgpack = (w.VERSION << 24 | 1).to_bytes(4, "big") + b"\xc1"
        event = w.encode(w.Event(1, b"x", 0, 1))
        hello = w.encode(w.Hello(0xBAD, "bad", "127.0.0.1", 9))
        for daemon in (address, sub_address):
            for junk in (oversized, wrong_version, not_msgpack, event, hello + b"\x00\x00"):
                _throw(daemon, junk)
        _fuzz(address, sub_address)
        assert status(address)["stats"]["malformed"] >= 4
        assert status(sub_address)["stats"]["malformed"] >= 4
        with pub_proc(address, "ok", "c0ffee", count=1, rate=10) as pub:
            assert pub.finish()[0] == 0
        code, out = sub.finish()
        assert code == 0
        assert json.loads(out)["data"] == "c0ffee"


def _fuzz(*addresses: str) -> None:
    frame = st.builds(
        lambda version, body: (version << 24 | len(body)).to_bytes(4, "big") + body,
        st.sampled_from([w.VERSION, w.VERSION, 0, 2, 255]),
        st.binary(max_size=64),
    )

    @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
    @given(
        st.sampled_from(addresses),
        st.one_of(st.binary(max_size=256), st.lists(frame, min_size=1, max_size=4).map(b"".join)),
    )
    def throw(address: str, data: bytes) -> None:
        _throw(address, data)

    throw()


def test_cli_errors_are_clear() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = f"127.0.0.1:{s.getsockname()[1]}"
    with Proc("sub", "x", "--broker", free, "--join-timeout", "0.5") as sub:
        code, _ = sub.finish()
        assert code == 2
        assert any(f"nothing listened at {free}" in line for line in sub.stderr_lines)
    with Proc("status", free, "--timeout", "1") as st_proc:
        assert st_proc.finish()[0] == 2
    with Proc("pub", "x", "00", "--broker", free, "--can", "virtual:x") as both:
        assert both.finish()[0] == 2
        assert any("not allowed with" in line for line in both.stderr_lines)
    with Proc("broker", "--listen", "127.0.0.1:http") as bad:
        assert bad.finish()[0] == 2
        assert any("HOST:PORT" in line for line in bad.stderr_lines)


def test_every_event_is_printed_or_reported_lost(tmp_path: Path) -> None:
    """A subscriber frozen while 20,000 events fly: the events its full queue lost, `ups pub`
    reports as dropped and `ups sub`, once it runs again, as missing (sequence gaps); both
    exit 1, and what was printed plus what was reported lost is every event."""
    # The TCP-ECB's liveness outlasts the freeze, however long the publisher takes to start
    # (a subscriber taken for dead and back is another story). The subscriber prints into a
    # file: it never waits for this process to read a pipe, which could hold it up past its
    # publisher's close, when what is still queued for it is dropped.
    broker, address = start_tcp_broker("--recovery", "0", "--liveness", "60")
    count = 20_000
    data = "ab" * 500
    out_file = tmp_path / "sub.out"
    with broker:
        args = ["sub", "bulk", "--broker", address, "--node-id", hex(SUB_ID), "--timeout", "60"]
        with Proc(*args, stdout=out_file) as sub:
            sub.wait_for_line("subscribed to")
            (node,) = status(address)["nodes"]
            sub.pause()
            with pub_proc(address, "bulk", data, count=count, rate=20_000) as pub:
                pub.wait_for_line(r"dropped \d+ events for subscriber")
                sub.resume()  # while the publisher still runs: its queue drains to us
                code, _ = pub.finish(timeout=60)
            assert code == 1, "".join(pub.stderr_lines)
            dropped = [line for line in pub.stderr_lines if "events were dropped" in line]
            assert dropped, "".join(pub.stderr_lines)
            at_pub = int(dropped[0].split("ups pub: ")[1].split()[0])
            # Done when what the publisher did not drop is printed or dropped from the full
            # queue of the subscriber, which then says, at SIGTERM, what it lost.
            with out_file.open("rb") as printed:
                lines = 0

                def accounted() -> bool:
                    nonlocal lines
                    lines += printed.read().count(b"\n")
                    in_queue = status(node["address"])["stats"]["dropped"]
                    return lines + in_queue >= count - at_pub

                wait_until(accounted, timeout=30)
            code_sub = sub.stop()
            out = out_file.read_text()
    lost = re.search(
        r"lost (\d+) events: (\d+) dropped .*, (\d+) missing", "".join(sub.stderr_lines)
    )
    assert code_sub == 1 and lost, "".join(sub.stderr_lines)
    total, _in_queue, skipped = (int(x) for x in lost.groups())
    assert skipped == at_pub  # each event the publisher dropped, the subscriber counted
    assert len(out.splitlines()) + total == count  # nothing vanished uncounted
