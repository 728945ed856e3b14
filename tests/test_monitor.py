"""``ups monitor`` with real processes: channels by name with their rate and decoded last
value, nodes joining and leaving; on CAN, etags, names from the catalog and the bus load,
while only listening."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import pytest

from .procs import ROOT, Proc, private_multicast_bus, start_tcp_broker

CATALOG = str(ROOT / "examples" / "robots.toml")


def snapshots(out: str) -> list[dict]:
    return [json.loads(line) for line in out.splitlines()]


def test_monitor_shows_channels_values_and_nodes_coming_and_going() -> None:
    broker, address = start_tcp_broker("--recovery", "0", "--liveness", "1")
    with (
        broker,
        Proc(
            "pub",
            "robot/speed",
            "speed=42",
            "--broker",
            address,
            "--catalog",
            CATALOG,
            "--count",
            "100000",
            "--rate",
            "50",
        ),  # fmt: skip
        Proc(
            "monitor",
            "--broker",
            address,
            "--catalog",
            CATALOG,
            "--json",
            "--interval",
            "0.5",
            "--duration",
            "60",
        ) as monitor,  # fmt: skip
    ):
        gone = "0x00000000000000b2"

        def seen() -> list[dict]:
            return snapshots("".join(monitor.stdout_lines[:-1]))  # whole lines only

        def until(done: Callable[[list[dict]], bool]) -> None:
            deadline = time.monotonic() + 25
            while not done(seen()):
                assert monitor.popen.poll() is None, monitor.stderr_lines
                assert time.monotonic() < deadline, seen()[-1:]
                time.sleep(0.1)

        # A second publisher comes, stays until the monitor has shown its value (it finds the
        # channel in the TCP-ECB's status, polled every second), then goes.
        with Proc(
            "pub",
            "robot/distance",
            "distance=7",
            "--broker",
            address,
            "--catalog",
            CATALOG,
            "--node-id",
            "0xb2",
            "--count",
            "100000",
            "--rate",
            "20",
        ) as short:
            until(lambda snaps: any(c["name"] == "robot/distance" and c["last"] == "distance=7 cm"
                                    for s in snaps for c in s["channels"]))  # fmt: skip
            assert short.stop() == 0, short.stderr_lines
        until(lambda snaps: any(any(n["key"] == gone and not n["alive"] for n in s["nodes"])
                                for s in snaps))  # fmt: skip
    snaps = seen()
    last = snaps[-1]
    speed = next(c for c in last["channels"] if c["name"] == "robot/speed")
    assert speed["last"] == "speed=42 cm/s" and speed["values"] == {"speed": 42}
    assert speed["rate"] > 10 and speed["count"] > 10
    assert any(c["name"] == "robot/distance" and c["last"] == "distance=7 cm"
               for s in snaps for c in s["channels"])  # fmt: skip
    recent = "\n".join(last["recent"])
    assert f"joined: ups-pub ({gone})" in recent
    assert f"disconnected: ups-pub ({gone})" in recent or f"left: ups-pub ({gone})" in recent


def test_monitor_plain_text_is_a_table() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        Proc(
            "pub",
            "robot/speed",
            "speed=5",
            "--broker",
            address,
            "--catalog",
            CATALOG,
            "--count",
            "100000",
            "--rate",
            "50",
        ),  # fmt: skip
    ):
        broker.wait_for_line(r"\(ups-pub\) joined")  # publishing: its events are there to see
        monitor = Proc("monitor", "--broker", address, "--catalog", CATALOG, "--plain",
                       "--interval", "1", "--duration", "3.5")  # fmt: skip
        code, out = monitor.finish()
    assert code == 0, monitor.stderr_lines
    assert out.startswith(f"ups monitor  tcp {address}")
    assert any(line.startswith("robot/speed") and "speed=5 cm/s" in line
               for line in out.splitlines())  # fmt: skip


@pytest.mark.netns
def test_monitor_of_a_can_bus_only_listens(tmp_path: object) -> None:
    bus = private_multicast_bus()
    db = str(tmp_path) + "/ecb.db"  # type: ignore[operator]

    def speed_of(snap: dict) -> dict | None:
        return next((c for c in snap["channels"] if c["name"] == "robot/speed"), None)

    with Proc("can-broker", "--can", bus, "--db", db, "--recovery", "0.2") as ecb:
        ecb.wait_for_line("CAN-ECB on")
        with Proc("pub", "robot/speed", "speed=9", "--can", bus, "--catalog", CATALOG,
                  "--count", "100000", "--rate", "100"):  # fmt: skip
            ecb.wait_for_line(r"has TxNode 0x00")  # joined: its events follow
            with Proc("monitor", "--can", bus, "--db", db, "--catalog", CATALOG,
                      "--json", "--interval", "1", "--duration", "60") as monitor:  # fmt: skip
                # a snapshot of at least a second of the publisher's events, whenever it comes
                deadline = time.monotonic() + 30
                while True:
                    snaps = snapshots("".join(monitor.stdout_lines[:-1]))  # whole lines only
                    seen = speed_of(snaps[-1]) if snaps else None
                    if seen and seen["count"] >= 100:
                        break
                    assert monitor.popen.poll() is None, monitor.stderr_lines
                    assert time.monotonic() < deadline, snaps[-1:]
                    time.sleep(0.1)
                code = monitor.stop()  # SIGTERM: a normal way to stop it
        assert code == 0, monitor.stderr_lines
        # the CAN-ECB gave out one TxNode: the publisher's; the monitor never joined
        assert ecb.stop() == 0
        assert not any("has TxNode 0x01" in line for line in ecb.stderr_lines), ecb.stderr_lines
    last = snaps[-1]
    speed = speed_of(last)
    assert speed is not None
    assert speed["etag"] == "0x0010" and speed["last"] == "speed=9 cm/s" and speed["rate"] > 20
    assert last["bus_load"] > 0
    assert [n["txnode"] for n in last["nodes"]] == ["0x00"]


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (("monitor", "--can", "virtual:x", "--db", "/nonexistent.db"), "no CAN-ECB database"),
        (("monitor", "--broker", "127.0.0.1:1", "--timeout", "0.5", "--plain"), "TCP-ECB"),
        (("monitor", "--broker", "127.0.0.1:1", "--catalog", "/none.toml"), "cannot read"),
    ],
)
def test_monitor_bad_input_is_one_line_and_exit_2(args: tuple[str, ...], says: str) -> None:
    proc = Proc(*args)
    code, _ = proc.finish()
    assert code == 2 and len(proc.stderr_lines) == 1 and says in proc.stderr_lines[0], (
        proc.stderr_lines
    )


def test_monitor_that_never_reached_its_broker_within_its_duration_says_so() -> None:
    """Empty tables are not a result: exit 2, as ``ups ls`` does (it used to exit 0)."""
    proc = Proc("monitor", "--broker", "127.0.0.1:1", "--duration", "1", "--plain")
    code, out = proc.finish()
    assert code == 2 and "CHANNEL" in out, proc.stderr_lines
    assert "nothing answered at 127.0.0.1:1 within --duration 1 s" in proc.stderr_lines[-1]


def test_monitor_outlives_a_restart_of_the_tcp_ecb() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    port = int(address.rpartition(":")[2])
    with Proc("monitor", "--broker", address, "--json", "--interval", "0.3",
              "--duration", "60") as monitor:  # fmt: skip

        def recent() -> str:
            snaps = snapshots("".join(monitor.stdout_lines[:-1]))
            return "\n".join(snaps[-1]["recent"]) if snaps else ""

        def until(text: str) -> None:
            deadline = time.monotonic() + 20
            while text not in recent():
                assert monitor.popen.poll() is None, monitor.stderr_lines
                assert time.monotonic() < deadline, recent()
                time.sleep(0.1)

        deadline = time.monotonic() + 20
        while len(monitor.stdout_lines) < 2:  # joined, and a snapshot printed whole
            assert time.monotonic() < deadline and monitor.popen.poll() is None
            time.sleep(0.1)
        assert broker.stop() == 0
        until("no status from the TCP-ECB")
        again, _ = start_tcp_broker("--recovery", "0", port=port)
        with again:
            until("the TCP-ECB answers again")
