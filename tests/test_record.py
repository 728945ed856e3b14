"""``ups record``, ``decode``, ``replay`` and ``dbc`` with real processes: a recording replayed
onto a bus whose etags were bound in another order delivers every event on its own channel;
a python-can logger's capture decodes in UPS terms; the DBC decodes a recorded frame."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import can
import cantools
import pytest

from .procs import ROOT, Proc, private_multicast_bus, start_tcp_broker

CATALOG = """\
[channel."robot/speed"]
fields = [
    { name = "left", type = "i16", scale = 0.001, unit = "m/s" },
    { name = "right", type = "i16", scale = 0.001, unit = "m/s" },
]

[channel."robot/distance"]
fields = [{ name = "d", type = "u16", scale = 0.01, unit = "m" }]
"""
SPEED, DISTANCE = "e803d007", "0a00"  # left=1 right=2 m/s; d=0.1 m
N_SPEED, N_DISTANCE = 20, 10


def ups(*args: str) -> tuple[int, str, list[str]]:
    proc = Proc(*args)
    code, out = proc.finish(timeout=30)
    return code, out, proc.stderr_lines


def publish(network: str, where: str) -> None:
    """``ups pub`` of robot/speed, then robot/distance: bound in that order."""
    for channel, data, count in (("robot/speed", SPEED, N_SPEED),
                                 ("robot/distance", DISTANCE, N_DISTANCE)):  # fmt: skip
        code, _, err = ups("pub", channel, data, network, where, "--count", str(count),
                           "--rate", "200")  # fmt: skip
        assert code == 0, err


def subscribers(network: str, where: str) -> tuple[Proc, Proc]:
    """``ups sub`` of robot/distance, then robot/speed: bound the other way round."""
    subs = []
    for channel, count in (("robot/distance", N_DISTANCE), ("robot/speed", N_SPEED)):
        sub = Proc("sub", channel, network, where, "--count", str(count), "--json",
                   "--timeout", "30")  # fmt: skip
        sub.wait_for_line("subscribed to")
        subs.append(sub)
    return subs[0], subs[1]


def each_on_its_own_channel(distance: Proc, speed: Proc) -> None:
    for sub, name, data, count in ((distance, "robot/distance", DISTANCE, N_DISTANCE),
                                   (speed, "robot/speed", SPEED, N_SPEED)):  # fmt: skip
        code, out = sub.finish(timeout=30)
        assert code == 0, sub.stderr_lines
        events = [json.loads(line) for line in out.splitlines()]
        assert len(events) == count
        assert {(e["channel"], e["data"]) for e in events} == {(name, data)}


def test_a_tcp_recording_decodes_and_replays_onto_another_network(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog.toml"
    catalog.write_text(CATALOG)
    recording = str(tmp_path / "run.blf")
    first, address = start_tcp_broker("--recovery", "0")
    with first, Proc("record", recording, "robot/speed", "robot/distance", "--broker", address,
                     "--count", str(N_SPEED + N_DISTANCE)) as rec:  # fmt: skip
        rec.wait_for_line("recording")
        publish("--broker", address)
        code, _ = rec.finish()
        assert code == 0, rec.stderr_lines
    assert f"{N_SPEED + N_DISTANCE} events on 2 channels" in rec.stderr_lines[-1]

    code, out, err = ups("decode", recording, "--catalog", str(catalog))
    assert code == 0, err
    lines = out.splitlines()
    assert sum("robot/speed  left=1 m/s right=2 m/s" in line for line in lines) == N_SPEED
    assert sum("robot/distance  d=0.1 m" in line for line in lines) == N_DISTANCE

    second, address = start_tcp_broker("--recovery", "0")
    with second:
        distance, speed = subscribers("--broker", address)
        with distance, speed:
            code, _, err = ups("replay", recording, "--broker", address, "--speed", "4")
            assert code == 0, err
            assert f"published {N_SPEED + N_DISTANCE} of {N_SPEED + N_DISTANCE}" in "".join(err)
            each_on_its_own_channel(distance, speed)


@pytest.mark.netns
def test_a_can_recording_replays_by_channel_onto_a_bus_bound_the_other_way(
    tmp_path: Path,
) -> None:
    catalog = tmp_path / "catalog.toml"
    catalog.write_text(CATALOG)
    recording = tmp_path / "run.log"
    bus_a, bus_b = private_multicast_bus(), private_multicast_bus()
    db_a = str(tmp_path / "a.db")
    logger = subprocess.Popen(  # python-can's own logger, beside ups record
        [sys.executable, "-m", "can.logger", "-i", "udp_multicast", "-c", "239.74.163.2",
         "--bus-kwargs", f"port={bus_a.rpartition('=')[2]}", "-f", str(tmp_path / "capture.log")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
        # Ctrl-C must reach it even when this test runs in a background job, which starts
        # with SIGINT ignored (and so would the logger, and never flush)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        assert logger.stdout is not None
        assert "Connected to" in logger.stdout.readline()
        with Proc("can-broker", "--can", bus_a, "--db", db_a, "--recovery", "0.2") as ecb:
            ecb.wait_for_line("CAN-ECB on")
            count = str(N_SPEED + N_DISTANCE)
            with Proc(
                "record", str(recording), "--can", bus_a, "--db", db_a, "--count", count
            ) as rec:
                rec.wait_for_line("recording")
                publish("--can", bus_a)
                code, _ = rec.finish()
                assert code == 0, rec.stderr_lines
    finally:
        logger.send_signal(signal.SIGINT)  # python-can's logger flushes on Ctrl-C
        logger.wait(timeout=10)
    side = json.loads(Path(f"{recording}.ups.json").read_text())
    assert sorted(side["etags"]) == ["0x0010", "0x0011"]  # speed, then distance

    db_b = str(tmp_path / "b.db")
    with Proc("can-broker", "--can", bus_b, "--db", db_b, "--recovery", "0.2") as ecb:
        ecb.wait_for_line("CAN-ECB on")
        distance, speed = subscribers("--can", bus_b)  # distance gets 0x0010 here
        with distance, speed:
            code, _, err = ups("replay", str(recording), "--can", bus_b, "--speed", "4")
            assert code == 0, err
            each_on_its_own_channel(distance, speed)

    # python-can's capture of the same run, read with the CAN-ECB's database and the catalog
    code, out, err = ups("decode", str(tmp_path / "capture.log"), "--db", db_a,
                         "--catalog", str(catalog), "--management")  # fmt: skip
    assert code == 0, err
    assert (
        sum("robot/speed  left=1 m/s right=2 m/s" in line for line in out.splitlines()) == N_SPEED
    )
    assert "Bind etag 0x0010 = robot/speed" in out

    # a DBC from the recording decodes a recorded frame
    dbc = tmp_path / "bus.dbc"
    code, _, err = ups("dbc", "--recording", str(recording), "--catalog", str(catalog),
                       "-o", str(dbc))  # fmt: skip
    assert code == 0, err
    database = cantools.database.load_file(str(dbc))
    frame = next(m for m in can.LogReader(str(recording)) if m.data.hex() == SPEED)
    assert database.decode_message(frame.arbitration_id, frame.data) == {"left": 1.0, "right": 2.0}
    assert database.get_message_by_frame_id(frame.arbitration_id).name.startswith("robot_speed")


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (("record", "out.txt", "--broker", "127.0.0.1:1"), "the log format is chosen by"),
        (("decode", "missing.asc"), "no such file"),
        (("decode", "garbage.log"), "not a log python-can can read"),
        (("replay", "run.asc", "--broker", "127.0.0.1:1"), "malformed bindings"),
        (("dbc", "-o", "x.dbc"), "which frames?"),
        (("decode", "other.asc", "--catalog", "bad.toml"), "catalog bad.toml"),
        (("decode", "cut.blf"), "not a log python-can can read"),
        (("replay", "neg.log", "--broker", "127.0.0.1:1"), "is not 0x and 1..16 hex digits"),
        (("record", "keep.blf", "--broker", "127.0.0.1:1", "--timeout", "0.5"), "TCP-ECB"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, args: tuple[str, ...], says: str) -> None:
    (tmp_path / "garbage.log").write_bytes(b"\x00\xff not a log\n")
    (tmp_path / "run.asc").write_text("")
    (tmp_path / "other.asc").write_text("")
    (tmp_path / "run.asc.ups.json").write_text('{"format": "ups-bindings/1", "etags": 3}')
    (tmp_path / "bad.toml").write_text('[channel."x"]\nfields = [{ name = "a", type = "u7" }]\n')
    with can.Logger(str(tmp_path / "keep.blf")) as log:  # a recording that must stay as it is
        for i in range(50):
            log(can.Message(timestamp=i, arbitration_id=0x1000_0010, data=bytes([i])))
    kept = (tmp_path / "keep.blf").read_bytes()
    (tmp_path / "cut.blf").write_bytes(kept[:17])
    (tmp_path / "neg.log").write_text("(1.0) vcan0 10000010#01\n")
    (tmp_path / "neg.log.ups.json").write_text(
        '{"format": "ups-bindings/1", "etags": {"0x0010": "-0x1"}, "txnodes": {}}'
    )
    proc = Proc(*args, cwd=tmp_path, env={"UPS_CAN": ""})
    code, _ = proc.finish()
    assert code == 2
    assert len(proc.stderr_lines) == 1 and says in proc.stderr_lines[0], proc.stderr_lines
    assert (tmp_path / "keep.blf").read_bytes() == kept  # a failed record destroys nothing
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # nor leaves a part


def test_a_dbc_of_odd_channel_names_loads_in_cantools(tmp_path: Path) -> None:
    from ups import name_to_uid
    from ups._bindings import Bindings
    from ups._catalog import Catalog
    from ups.tools.dbc import build

    names = ["vitesse/é", "a/b", "a.b", "a_b", "9lives"]
    bindings = Bindings(etags={0x10 + i: name_to_uid(n) for i, n in enumerate(names)})
    streams = {(0x80, 5, 0x10 + i): (name_to_uid(n), 2) for i, n in enumerate(names)}
    streams[(0x40, 5, 0x11)] = (name_to_uid("a/b"), 2)  # one channel at two priorities
    database, skipped = build(bindings, streams, Catalog())
    assert skipped == 0
    cantools.database.dump_file(database, str(tmp_path / "odd.dbc"))
    loaded = cantools.database.load_file(str(tmp_path / "odd.dbc"))
    labels = [m.name for m in loaded.messages]
    assert len(set(labels)) == len(names) + 1 and all(label.isascii() for label in labels)


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log"])
def test_large_events_record_decode_and_replay_whole(tmp_path: Path, suffix: str) -> None:
    """TCP/IP events of 9 bytes to 60 KiB are recorded as transfers of CAN FD frames, and
    read back whole by decode and replay."""
    sizes = (9, 64, 1000, 60_000)
    events = [bytes((i * 7 + n) & 0xFF for i in range(n)) for n in sizes]
    recording = str(tmp_path / f"big{suffix}")
    first, address = start_tcp_broker("--recovery", "0")
    with first, Proc("record", recording, "big", "--broker", address, "--count",
                     str(len(sizes))) as rec:  # fmt: skip
        rec.wait_for_line("recording")
        for data in events:
            code, _, err = ups("pub", "big", data.hex(), "--broker", address, "--count", "1")
            assert code == 0, err
        code, _ = rec.finish()
        assert code == 0, rec.stderr_lines

    code, out, err = ups("decode", recording, "--json")
    assert code == 0, err
    decoded = [json.loads(line) for line in out.splitlines()]
    got = [bytes.fromhex(e["data"]) for e in decoded if e.get("channel") == "big"]
    assert got == events

    second, address = start_tcp_broker("--recovery", "0")
    with second, Proc("sub", "big", "--broker", address, "--count", str(len(sizes)), "--json",
                      "--timeout", "30") as sub:  # fmt: skip
        sub.wait_for_line("subscribed to")
        code, _, err = ups("replay", recording, "--broker", address, "--speed", "4")
        assert code == 0, err
        code, out = sub.finish(timeout=30)
        assert code == 0, sub.stderr_lines
        assert [bytes.fromhex(json.loads(x)["data"]) for x in out.splitlines()] == events


@pytest.mark.netns
def test_dbc_names_the_channels_it_leaves_out_for_being_larger_than_a_frame(
    tmp_path: Path,
) -> None:
    """A channel larger than one frame goes as transfers on etags of its own, which no DBC
    message describes: ``ups dbc`` says which, instead of leaving them out without a word."""
    catalog = tmp_path / "catalog.toml"
    catalog.write_text(CATALOG + '\n[channel."robot/map"]\ndescription = "a map tile"\n')
    recording = tmp_path / "run.log"
    bus = private_multicast_bus()
    db = str(tmp_path / "ecb.db")
    big = bytes(range(100)).hex()
    with Proc("can-broker", "--can", bus, "--db", db, "--recovery", "0.2") as ecb:
        ecb.wait_for_line("CAN-ECB on")
        with Proc("record", str(recording), "--can", bus, "--db", db, "--count", "6") as rec:
            rec.wait_for_line("recording")
            for channel, data in (("robot/speed", SPEED), ("robot/map", big)):
                code, _, err = ups("pub", channel, data, "--can", bus, "--count", "3")
                assert code == 0, err
            code, _ = rec.finish()
            assert code == 0, rec.stderr_lines
        # the live bus too: a DBC of what is heard while the large channel is published
        with Proc("pub", "robot/map", big, "--can", bus, "--count", "100000", "--rate", "50"):
            code, _, err = ups("dbc", "--can", bus, "--db", db, "--catalog", str(catalog),
                               "--listen-for", "1", "-o", str(tmp_path / "live.dbc"))  # fmt: skip
        assert code == 0, err
        assert "larger than one frame: robot/map (100 B)" in "".join(err)
    dbc = tmp_path / "bus.dbc"
    code, _, err = ups("dbc", "--recording", str(recording), "--catalog", str(catalog),
                       "-o", str(dbc))  # fmt: skip
    assert code == 0, err
    said = "".join(err)
    assert "ups dbc: 1 messages in" in said, said  # robot/speed
    assert "left out: 1 channel larger than one frame: robot/map (100 B)" in said
    assert "show those frames as unknown" in said
    names = [m.name for m in cantools.database.load_file(str(dbc)).messages]
    assert len(names) == 1 and names[0].startswith("robot_speed")
