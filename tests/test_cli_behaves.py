"""The command line with real processes: bad input exits 2 with one line and no traceback, a
slow broker is announced, the environment gives defaults, and closing the output is a way to
stop."""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from .procs import ROOT, Proc
from .test_tcp_processes import start_tcp_broker

NO_NETWORK = {"UPS_BROKER": "", "UPS_CAN": "", "UPS_ZENOH": ""}


def one_line_error(proc: Proc) -> str:
    code, _ = proc.finish()
    text = "".join(proc.stderr_lines)
    assert code == 2, text
    assert "Traceback" not in text, text
    errors = [line for line in proc.stderr_lines if line.startswith(("ups ", "usage:"))]
    assert errors, text
    return text


def test_version_and_verbose_after_the_command() -> None:
    code, out = Proc("--version").finish()
    assert code == 0 and out.startswith("ups ")
    code, _ = Proc("certs", "ca", "-v", "--help").finish()
    assert code == 0


def test_a_port_in_use_is_one_line() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        text = one_line_error(Proc("broker", "--listen", f"127.0.0.1:{port}"))
        assert "address already in use" in text


#: a gateway that hosts no CAN-ECB: the hosted CAN-ECB's options are refused
EXTERNAL_CAN_ECB = [
    "gateway",
    "--can",
    "virtual:x",
    "--broker",
    "127.0.0.1:1",
    "--external-can-ecb",
]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["pub", "x", "00", "--broker", "127.0.0.1:1", "--rate", "-5"], "0 or more"),
        (["sub", "x", "--broker", "127.0.0.1:1", "--timeout", "-1"], "must be a finite number"),
        (["sub", "x", "--broker", "127.0.0.1:1", "--join-timeout", "0"], "above 0"),
        (["sub", "x", "--broker", "127.0.0.1:1", "--timeout", "inf"], "must be a finite number"),
        (["pub", "x", "00", "--broker", "127.0.0.1:1", "--rate", "nan"], "must be a finite"),
        (["sub", "x"], "which network?"),
        (["sub", "x", "--broker", "nohost:99999"], "expected HOST:PORT"),
        (["pub", "x", "zz", "--broker", "127.0.0.1:1"], "not hex digits"),
        (["pub", "x", "032", "--broker", "127.0.0.1:1"], "odd number of hex digits (3)"),
        (["sub", "x", "--zenoh", "127.0.0.1:7447"], "did you mean --zenoh tcp/127.0.0.1:7447"),
        (["can-broker", "--can", "virtual:x", "--db", "/proc/no/such.db"], "cannot use"),
        (["sub", "x", "--can", "nosuch:x"], "cannot open CAN bus"),
        (["sub", "x", "--can", "virtual:x,bogus=1"], "unknown option 'bogus'"),
        (["gateway", "--can", "virtual:x"], "--broker"),
        (["sub", "x", "--zenoh", "nonsense"], "bad Zenoh endpoint"),
        (["sub", "x", "--zenoh", "tcp/127.0.0.1:1", "--listen", "127.0.0.1:0"], "--listen is for"),
        (["sub", "x", "--can", "virtual:x", "--zenoh-config", "c.json5"], "for Zenoh nodes"),
        (["sub", "x", "--zenoh-config", "/no/such.json5"], "bad Zenoh config"),
        (["zenoh-router", "--listen", "nonsense"], "bad Zenoh endpoint"),
        (["status"], "ups status HOST:PORT"),
        (["status", "127.0.0.1:1", "--zenoh", "tcp/127.0.0.1:1"], "ups status HOST:PORT"),
        (
            ["gateway", "--can", "virtual:x", "--zenoh", "tcp/127.0.0.1:1", "--listen", ":0"],
            "--listen is for a",
        ),
        *[
            ([*EXTERNAL_CAN_ECB, option, value], f"{option} is for the CAN-ECB the gateway hosts")
            for option, value in (("--recovery", "0.5"), ("--db", "x.db"))
        ],
    ],
)
def test_bad_input_is_one_line(args: list[str], message: str) -> None:
    assert message in one_line_error(Proc(*args, env=NO_NETWORK))


def test_socketcan_on_a_kernel_without_it_says_so() -> None:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError:
        pass
    else:
        pytest.skip("this kernel has SocketCAN")
    text = one_line_error(Proc("sub", "x", "--can", "socketcan:vcan9", env=NO_NETWORK))
    assert "this kernel has no SocketCAN" in text and "udp_multicast" in text
    assert "Errno" not in text


def test_ups_sub_stopped_by_a_signal_says_how_many_events_it_printed() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("sub", "x", "--broker", address, env=NO_NETWORK) as sub:
        sub.wait_for_line("subscribed to x")
        sub.stop()
    assert "ups sub: stopped after 0 events" in "".join(sub.stderr_lines)


def test_a_missing_zenoh_router_is_announced_and_then_given_up() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here
    proc = Proc("sub", "x", "--zenoh", f"tcp/127.0.0.1:{port}", "--join-timeout", "2.5")
    proc.wait_for_line(f"waiting for the Zenoh router at tcp/127.0.0.1:{port}")
    assert "could not join the Zenoh router" in one_line_error(proc)


def test_a_missing_broker_is_announced_and_then_given_up() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here
    proc = Proc("sub", "x", "--broker", f"127.0.0.1:{port}", "--join-timeout", "2.5")
    proc.wait_for_line(f"waiting for the TCP-ECB at 127.0.0.1:{port}")
    assert f"nothing listened at 127.0.0.1:{port} within 2.5 s" in one_line_error(proc)


def test_the_environment_names_the_network_and_a_closed_pipe_stops_quietly() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    env = {"UPS_BROKER": address, "PYTHONPATH": str(ROOT)}
    with broker, Proc("pub", "env/x", "01", "--count", "100000", "--rate", "2000", env=env):
        reader = subprocess.Popen(  # no --broker: the environment's
            f"{sys.executable} -m upscli sub env/x --json | head -n 1",
            shell=True, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        out, err = reader.communicate(timeout=30)  # head leaves after one line: sub stops
        assert out.count("\n") == 1 and '"data": "01"' in out
        assert "Traceback" not in err, err


def test_bash_completion_knows_the_commands_and_their_options(tmp_path: Path) -> None:
    code, script = Proc("completion").finish()
    assert code == 0
    (tmp_path / "ups.bash").write_text(script)
    probe = (
        f"source {tmp_path / 'ups.bash'}\n"
        "COMP_WORDS=(ups su); COMP_CWORD=1; _ups; echo ${COMPREPLY[@]}\n"
        "COMP_WORDS=(ups sub --bro); COMP_CWORD=2; _ups; echo ${COMPREPLY[@]}\n"
        "COMP_WORDS=(ups broker --a); COMP_CWORD=2; _ups; echo ${COMPREPLY[@]}\n"
    )
    done = subprocess.run(["bash", "-c", probe], capture_output=True, text=True, timeout=30)
    assert done.stdout.split("\n")[:3] == ["sub", "--broker", "--acl"], done.stderr


def _options(parser: argparse.ArgumentParser) -> dict[str, list[tuple[str, ...]]]:
    """Each command's option strings and positional names, subcommands included."""
    out: dict[str, list[tuple[str, ...]]] = {}

    def walk(name: str, p: argparse.ArgumentParser) -> None:
        out[name] = sorted(tuple(a.option_strings) or (a.dest,) for a in p._actions)
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, child in action.choices.items():
                    walk(f"{name} {sub}", child)

    walk("ups", parser)
    return out


def test_each_command_is_built_alone_as_it_is_in_the_whole_command_line() -> None:
    """`ups CMD` builds only CMD's options (the others are listed, not built): what it builds
    must be what the whole command line (`ups completion`) has for CMD."""
    from upscli import _parser

    whole = _options(_parser())
    commands = [name.split()[1] for name in whole if name.count(" ") == 1]
    assert {"pub", "jaus", "jaus-ocu", "analyze", "console"} <= set(commands)
    for command in commands:
        alone = _options(_parser(only=command))
        mine = {k: v for k, v in whole.items() if k == f"ups {command}" or
                k.startswith(f"ups {command} ")}  # fmt: skip
        assert {k: v for k, v in alone.items() if k in mine} == mine, command
    listed = _options(_parser(only=""))
    assert set(listed) == {"ups", *(f"ups {c}" for c in commands)}  # every command, no options


def test_the_tools_lines_in_ups_help_are_their_modules_help() -> None:
    """``ups --help`` lists the tools without importing them: its lines must be theirs."""
    import importlib

    from ups import tools

    for name, line in tools.COMMANDS.items():
        assert line == importlib.import_module(f"ups.tools.{name}").HELP, name


def test_ups_sub_of_a_name_the_catalog_does_not_have_says_so() -> None:
    catalog = str(ROOT / "examples" / "robots.toml")
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("sub", "robot/sped", "--broker", address, "--catalog", catalog,
                      "--timeout", "1", env=NO_NETWORK) as sub:  # fmt: skip
        line = sub.wait_for_line("not in the catalog")
    assert "robot/sped is not in the catalog" in line and "did you mean robot/speed?" in line


@pytest.mark.parametrize(
    ("args", "usage", "meant"),
    [
        (["sub", "x", "--brokr", "127.0.0.1:1"], "usage: ups sub ", "did you mean --broker?"),
        (["pub", "x", "01", "--cann=virtual:x"], "usage: ups pub ", "did you mean --can?"),
        (["jaus-ocu", "discover", "--bogus"], "usage: ups jaus-ocu discover ", None),
    ],
)
def test_a_misspelt_option_shows_its_commands_usage_and_the_option_meant(
    args: list[str], usage: str, meant: str | None
) -> None:
    text = one_line_error(Proc(*args, env=NO_NETWORK))
    assert usage in text and "error: unrecognized arguments: --" in text
    assert "usage: ups [-h]" not in text  # not the top level's
    assert (meant in text) if meant else ("did you mean" not in text)


def test_ups_status_is_readable_by_default_and_json_with_json() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    catalog = str(ROOT / "examples" / "robots.toml")
    with broker, Proc("sub", "robot/*", "--broker", address, "--catalog", catalog,
                      env=NO_NETWORK) as sub:  # fmt: skip
        sub.wait_for_line("subscribed to robot/*")
        with Proc("pub", "robot/speed", "01", "--broker", address, "--count", "100000",
                  "--rate", "200", env=NO_NETWORK):  # fmt: skip
            sub.wait_for_line("robot/speed", stdout=True)  # delivered: both are in the tables
            code, raw = Proc("status", address, "--json", env=NO_NETWORK).finish()
            assert code == 0
            doc = json.loads(raw)
            code, text = Proc("status", address, env=NO_NETWORK).finish()
    assert code == 0 and not text.lstrip().startswith("{")
    lines = text.splitlines()
    assert lines[0] == f"ups-broker {doc['node_id']}"
    joined = doc["stats"]["joined"]
    assert f"joined {joined}" in text and "more at 0" in text  # counters: the ones not 0
    assert [line.split()[:2] for line in lines].count(["NODE_ID", "NAME"]) == 1
    rows = {line.split()[1]: line for line in lines if line.strip().startswith("0x")}
    assert {"ups-sub", "ups-pub", "robot/speed"} <= set(rows), text
    assert "robot/speed" in rows["ups-sub"] and "robot/speed" in rows["ups-pub"]  # by name
    assert "SUBSCRIBERS" in text and len(doc["nodes"]) == 2


def test_ups_status_renders_any_status_document() -> None:
    from ups.tools.status import render

    assert render([]) == "no UPS node or gateway answered"
    a = {"name": "a", "node_id": "0x1", "stats": {"x": 0, "y": 0, "z": 0, "w": 0}}
    b = {"name": "b", "node_id": "0x2", "peers": [{"node": "0x1", "sent": 3}]}
    text = render([a, b])
    assert text.split("\n\n")[0] == "a 0x1\n  stats:\n    4 counters, all 0"
    assert "peers (1):" in text and "NODE  SENT" in text and "0x1   3" in text
