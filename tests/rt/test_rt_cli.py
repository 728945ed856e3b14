"""The ``ups analyze`` command line (``ups.rt.cli``)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from ups.rt import cli

from .conftest import SAE_CSV

HEADER = "name,size_bytes,jitter_ms,period_ms,deadline_ms"


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _write(tmp_path: Path, text: str) -> str:
    path = tmp_path / "set.csv"
    path.write_text(text)
    return str(path)


def test_json_on_sae_tindell1994(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(
        capsys, str(SAE_CSV), "--bitrate", "250000", "--method", "tindell1994",
        "--id-bits", "11", "--json",
    )  # fmt: skip
    assert code == 0 and err == ""
    report = json.loads(out)
    messages = report["messages"]
    assert len(messages) == 53
    assert messages[0] == {
        "name": "14",
        "priority": 0,
        "transmission_time_ms": 0.252,
        "response_time_ms": 0.772,
        "deadline_ms": 5.0,
        "schedulable": True,
    }
    assert [m["name"] for m in messages[:4]] == ["14", "9", "49", "42"]
    assert report["method"] == "tindell1994" and report["bitrate"] == 250_000
    assert report["schedulable"] is True


def test_json_defaults_and_unbounded_response(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(capsys, str(SAE_CSV), "--bitrate", "125k", "--id-bits", "11", "--json")
    assert code == 0
    report = json.loads(out)
    assert report["method"] == "davis2007" and report["blocking"] == "max-frame"
    messages = report["messages"]
    assert messages[0]["response_time_ms"] == pytest.approx(1.7)  # 0.1 + 0.52 + 0.52
    assert messages[-1]["response_time_ms"] is None
    assert messages[-1]["schedulable"] is False
    assert isinstance(messages[7]["response_time_ms"], float)
    assert messages[7]["response_time_ms"] > messages[7]["deadline_ms"]  # reported anyway
    assert report["schedulable"] is False


def test_table_output(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(capsys, str(SAE_CSV), "--bitrate", "125000", "--id-bits", "11")
    assert code == 0
    lines = out.splitlines()
    assert "davis2007" in lines[0] and "125000 bit/s" in lines[0]
    assert lines[1].split()[:2] == ["message", "prio"]
    assert lines[2].split() == ["14", "0", "1", "0.52", "0.1", "50", "5", "1.7", "ok"]
    assert any(line.endswith("MISS") for line in lines)
    assert "unbounded" in out
    assert lines[-1].startswith("46 of 53 messages miss their deadlines")


def test_priority_column_and_assign(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        f"{HEADER},priority\nslow,8,0,10,10,7\nfast,8,0,1,1,2\n",
    )
    code, out, _ = _run(capsys, path, "--bitrate", "1M", "--id-bits", "11", "--json")
    assert code == 0
    messages = json.loads(out)["messages"]
    assert [m["name"] for m in messages] == ["slow", "fast"]
    assert messages[1]["response_time_ms"] == pytest.approx(0.27)
    assert [m["priority"] for m in messages] == [7, 2]  # the file's values
    code, out, _ = _run(capsys, path, "--assign", "audsley", "--json")
    assert code == 0
    assert [m["priority"] for m in json.loads(out)["messages"]] == [1, 0]


def test_assign_audsley_failure_exits_1(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    path = _write(tmp_path, f"{HEADER}\na,8,0,1,0.1\n")
    code, out, err = _run(capsys, path, "--assign", "audsley")
    assert code == 1 and out == ""
    assert "'a'" in err and "deadline" in err and len(err.splitlines()) == 1


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (None, "cannot read"),
        ("name,size_bytes,period_ms\na,1,10\n", "missing column(s) jitter_ms, deadline_ms"),
        (f"{HEADER}\na,1,0,ten,10\n", "period_ms 'ten' is not a number"),
        (f"{HEADER}\na,1,0,-5,10\n", "period_ms must be positive"),
        (f"{HEADER}\na,one,0,5,10\n", "size_bytes 'one' is not an integer"),
        (f"{HEADER}\na,9,0,5,10\n", "0..8"),
        (f"{HEADER}\na,1,0,5\n", "expected 5 columns"),
        (f"{HEADER}\na,1,0,5,5\na,1,0,5,5\n", "used twice"),
        (f"{HEADER}\n", "no messages"),
        ("", "no header"),
        (f"{HEADER},priority\na,1,0,5,5,x\n", "priority 'x' is not an integer"),
        (f"{HEADER},priority\na,1,0,5,5,1\nb,1,0,5,5,1\n", "priority 1 is given to both"),
    ],
)
def test_bad_input_is_one_line_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, content: str | None, needle: str
) -> None:
    path = str(tmp_path / "absent.csv") if content is None else _write(tmp_path, content)
    code, out, err = _run(capsys, path)
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1
    assert err.startswith("ups analyze: error: ")
    assert needle in err
    assert "Traceback" not in err


def test_bad_bitrate_is_rejected_by_argparse(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as caught:
        cli.main([str(SAE_CSV), "--bitrate", "fast"])
    assert caught.value.code == 2
    assert "invalid bit rate" in capsys.readouterr().err


def test_add_arguments_on_a_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    """How the ``ups`` command wires it: a subparser, then ``run``."""
    parser = argparse.ArgumentParser(prog="ups")
    commands = parser.add_subparsers(dest="command", required=True)
    cli.add_arguments(commands.add_parser("analyze"))
    args = parser.parse_args(["analyze", str(SAE_CSV), "--id-bits", "11", "--json"])
    assert cli.run(args) == 0
    assert json.loads(capsys.readouterr().out)["bitrate"] == 500_000


def test_python_dash_m() -> None:
    for module in ("ups.rt.cli", "ups.rt"):
        done = subprocess.run(
            [sys.executable, "-m", module, str(SAE_CSV), "--id-bits", "11", "--json"],
            capture_output=True,
            text=True,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        assert len(json.loads(done.stdout)["messages"]) == 53


def test_a_channel_catalog_is_analysed_like_its_csv(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    catalog = tmp_path / "channels.toml"
    catalog.write_text(
        '[channel."a"]\nfields = [{ name = "x", type = "u32" }]\npriority = 3\n'
        "realtime = { period = 0.01, deadline = 0.005 }\n"
        '[channel."b"]\nfields = [{ name = "x", type = "u64" }]\npriority = 2\n'
        "realtime = { period = 0.005, deadline = 0.005, jitter = 0.001 }\n"
        '[channel."best-effort"]\nfields = [{ name = "x", type = "u8" }]\n'
    )
    csv = _write(tmp_path, f"{HEADER},priority\na,4,0,10,5,3\nb,8,1,5,5,2\n")
    code, from_catalog, err = _run(capsys, str(catalog), "--json")
    assert code == 0, err
    code, from_csv, err = _run(capsys, csv, "--json")
    assert code == 0, err
    assert json.loads(from_catalog)["messages"] == json.loads(from_csv)["messages"]
    catalog.write_text('[channel."a"]\nfields = [{ name = "t", type = "str" }]\n'
                       "realtime = { period = 0.01 }\n")  # fmt: skip
    code, _, err = _run(capsys, str(catalog))
    assert code == 2 and "payload has no fixed size" in err


def test_catalog_times_are_read_as_written(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """0.00104 s is 1.04 ms exactly: a float product would be 1.0399999999999998, and a
    message whose response time is exactly its deadline would wrongly miss it."""
    catalog = tmp_path / "c.toml"
    catalog.write_text("".join(
        f'[channel."m{i}"]\nfields = [{{ name = "x", type = "u8" }}]\npriority = {i + 2}\n'
        "realtime = { period = 0.01, deadline = 0.00104 }\n"
        for i in range(4)
    ))  # fmt: skip
    csv = _write(tmp_path, f"{HEADER},priority\n" + "".join(
        f"m{i},1,0,10,1.04,{i + 2}\n" for i in range(4)))  # fmt: skip
    code, from_catalog, _ = _run(capsys, str(catalog), "--json")
    code2, from_csv, _ = _run(capsys, csv, "--json")
    assert code == code2 == 0
    assert json.loads(from_catalog)["messages"] == json.loads(from_csv)["messages"]
    catalog.write_text('[channel."e"]\nrealtime = { period = 0.01 }\n')
    code, _, err = _run(capsys, str(catalog))
    assert code == 2 and "no fixed size" in err


def _responses(capsys: pytest.CaptureFixture[str], *extra: str) -> dict[str, dict[str, object]]:
    code, out, err = _run(capsys, str(SAE_CSV), "--bitrate", "500k", "--json", *extra)
    assert code == 0 and err == ""
    return {m["name"]: m for m in json.loads(out)["messages"]}


def test_node_cycles_put_the_nodes_work_into_the_analysis(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """RECEIVE cycles lengthen every response by their time exactly; SEND cycles are queuing
    jitter, which every message's own response includes (and may delay lower priorities);
    0,0 changes nothing."""
    plain = _responses(capsys)
    assert _responses(capsys, "--node-cycles", "0,0") == plain
    received = _responses(capsys, "--node-cycles", "0,4800", "--node-mhz", "48")  # 0.1 ms
    for name, m in plain.items():
        assert received[name]["response_time_ms"] == pytest.approx(m["response_time_ms"] + 0.1)
        assert received[name]["deadline_ms"] == m["deadline_ms"]
    sent = _responses(capsys, "--node-cycles", "9600")  # 0.2 ms at the default 48 MHz
    for name, m in plain.items():
        assert sent[name]["response_time_ms"] >= m["response_time_ms"] + 0.2 - 1e-9
    slow = _responses(capsys, "--node-cycles", "0,220000")  # 4.58 ms: the 5 ms deadlines miss
    assert not slow["9"]["schedulable"] and plain["9"]["schedulable"]
    code, out, _ = _run(capsys, str(SAE_CSV), "--node-cycles", "1652,2019")
    assert code == 0 and "the nodes' own work: 34.4 us to send (in J), 42.1 us to receive" in out


def test_node_cycles_that_leave_the_bus_no_time_are_an_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, _, err = _run(capsys, str(SAE_CSV), "--node-cycles", "0,480000")  # 10 ms > 5 ms
    assert code == 2
    assert "14: its deadline (5 ms) leaves the bus no time after the receiving node's work" in err
    for bad in ("1,2,3", "x", "-1", ""):
        with pytest.raises(SystemExit):
            cli.main([str(SAE_CSV), "--node-cycles", bad])
        assert "expected SEND or SEND,RECEIVE cycles" in capsys.readouterr().err
