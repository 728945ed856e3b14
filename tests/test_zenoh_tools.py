"""The operators' tools on a Zenoh network, as processes: ``ups ls``, ``monitor``, ``record``
(then ``decode`` and ``replay``) with ``--zenoh``, through a ``ups zenoh-router``."""

from __future__ import annotations

import json
import time
from pathlib import Path

from ups import name_to_uid

from .procs import Proc
from .test_monitor import CATALOG as ROBOTS
from .test_monitor import snapshots
from .test_record import CATALOG, N_DISTANCE, N_SPEED, each_on_its_own_channel, publish, subscribers
from .test_record import ups as run
from .test_zenoh import free_port
from .test_zenoh_processes import start_router


def test_ls_lists_the_nodes_channels_and_rates_of_a_zenoh_network() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with (
        start_router(endpoint),
        Proc("sub", "robot/speed", "0x1234", "--zenoh", endpoint, "--node-id", "0x51") as sub,
    ):
        sub.wait_for_line("subscribed to")
        with Proc("pub", "robot/speed", "01", "--zenoh", endpoint, "--node-id", "0x52",
                  "--count", "100000", "--rate", "50"):  # fmt: skip
            deadline = time.monotonic() + 30
            while True:  # until the publisher has joined and ls sees it
                code, out, err = run("ls", "--zenoh", endpoint, "--json", "--rates")
                assert code == 0, err
                table = json.loads(out)
                if len(table["nodes"]) == 2 or time.monotonic() > deadline:
                    break
    nodes = {n["node_id"]: n for n in table["nodes"]}
    sub_id, pub_id = f"0x{0x51:016x}", f"0x{0x52:016x}"
    assert set(nodes) == {sub_id, pub_id}
    assert (nodes[sub_id]["name"], nodes[sub_id]["subscribed"]) == ("ups-sub", 2)
    assert (nodes[pub_id]["name"], nodes[pub_id]["published"]) == ("ups-pub", 1)
    channels = {c["uid"]: c for c in table["channels"]}
    speed = channels[f"0x{name_to_uid('robot/speed'):016x}"]
    assert speed["name"] == "robot/speed"
    assert (speed["publishers"], speed["subscribers"]) == ([pub_id], [sub_id])
    assert speed["events_per_s"] > 0
    assert channels["0x0000000000001234"]["publishers"] == []


def test_monitor_follows_a_zenoh_network() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with (
        start_router(endpoint),
        Proc("pub", "robot/speed", "speed=42", "--zenoh", endpoint, "--catalog", ROBOTS,
             "--count", "100000", "--rate", "50"),
        Proc("monitor", "--zenoh", endpoint, "--catalog", ROBOTS, "--json", "--interval", "0.5",
             "--duration", "30") as monitor,
    ):  # fmt: skip
        deadline = time.monotonic() + 25

        def speed() -> dict | None:  # type: ignore[type-arg]
            for snap in reversed(snapshots("".join(monitor.stdout_lines[:-1]))):
                for channel in snap["channels"]:
                    if channel["name"] == "robot/speed" and channel["count"] > 10:
                        return dict(channel)
            return None

        while (seen := speed()) is None:
            assert time.monotonic() < deadline, monitor.stdout_lines[-1:]
            time.sleep(0.1)
    assert seen["last"] == "speed=42 cm/s" and seen["rate"] > 10
    assert snapshots(monitor.stdout_lines[0])[0]["network"] == "zenoh"


def test_a_zenoh_recording_decodes_and_replays(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog.toml"
    catalog.write_text(CATALOG)
    recording = str(tmp_path / "run.blf")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with start_router(endpoint):
        with Proc("record", recording, "robot/speed", "robot/distance", "--zenoh", endpoint,
                  "--count", str(N_SPEED + N_DISTANCE)) as rec:  # fmt: skip
            rec.wait_for_line("recording")
            publish("--zenoh", endpoint)
            code, _ = rec.finish()
            assert code == 0, rec.stderr_lines
        assert f"{N_SPEED + N_DISTANCE} events on 2 channels" in rec.stderr_lines[-1]
        code, out, err = run("decode", recording, "--catalog", str(catalog))
        assert code == 0, err
        assert sum("robot/speed  left=1 m/s right=2 m/s" in ln for ln in out.splitlines()) == 20
        distance, speed = subscribers("--zenoh", endpoint)
        with distance, speed:
            code, _, err = run("replay", recording, "--zenoh", endpoint, "--speed", "4")
            assert code == 0, err
            each_on_its_own_channel(distance, speed)
