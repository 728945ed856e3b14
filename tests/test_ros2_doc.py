"""docs/ros2.md: its worked example, computed with the bridge's own code from the demo robot's
map (every key, token, GID, payload and attachment it shows); its recipe's commands, as the
CLI parses them (every ``ups`` command and option, the extras, the scripts); its forwarding
rule, the one tests/test_ros2_processes.py shows."""

from __future__ import annotations

import itertools
import os
import re
import shlex
import tomllib

import pytest

from ups.ros2 import RMW_ZENOH_COMMIT, attachment, entity_token, gid, load_map, node_token
from ups.ros2._rmw import PUBLISHER, SUBSCRIPTION
from upscli import _parser, main

from .procs import ROOT

DOC = (ROOT / "docs" / "ros2.md").read_text()
RECIPE = DOC[DOC.index("## A recipe") : DOC.index("The format was taken from")]
EXTRAS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
ZID = "5c1e0f7a9b3d42e8a1f06c2d7e9b8a34"


def spaced(data: bytes) -> str:
    return data.hex(" ")


def test_the_worked_example_is_what_the_bridge_makes() -> None:
    bridge = load_map(ROOT / "examples" / "robot.ros2.toml")
    index = next(i for i, t in enumerate(bridge.topics) if t.topic == "/robot/max_speed")
    topic = bridge.topics[index]
    assert index + 1 == 4  # "the map's fourth: publisher 7, subscription 8"
    publisher, subscription = 2 * (index + 1) - 1, 2 * (index + 1)
    assert f"\n{topic.key}\n" in DOC
    assert f"\n{node_token(0, ZID, 0, '/', bridge.node)}\n" in DOC
    tokens = [
        entity_token(0, ZID, 0, entity, kind, "/", bridge.node, topic.topic, topic.type,
                     topic.type_hash, topic.qos)
        for entity, kind in ((publisher, PUBLISHER), (subscription, SUBSCRIPTION))
    ]  # fmt: skip
    assert all(f"\n{token}\n" in DOC for token in tokens)
    who = gid(tokens[0])
    assert f"XXH3-128 of its token: `{spaced(who)}`" in DOC
    payload = topic.ros_payload(bytes.fromhex("0032"), 1_700_000_000.0)
    assert payload == bytes.fromhex("00010000" + "000000000000e03f")
    assert f"| `{spaced(payload[:4])}` | encapsulation" in DOC
    assert f"| `{spaced(payload[4:])}` | `data` (float64)" in DOC
    assert topic.ups_payload(payload) == b"\x00\x32"
    extra = attachment(1, 1_700_000_000 * 10**9, who)
    rows = [extra[:8], extra[8:16], extra[16:17], extra[17:]]
    assert all(f"| `{spaced(row)}` |" in DOC for row in rows)
    assert DOC.count(RMW_ZENOH_COMMIT) >= 2


def test_the_forwarding_rule_is_the_one_the_processes_test_shows() -> None:
    """UPS -> ROS opens for any Zenoh subscriber whose key expression matches, ``**`` too, as
    tests/test_ros2_processes.py shows with real processes (the page used to say only a ROS
    subscriber of the exact key)."""
    from . import test_ros2_processes

    assert hasattr(test_ros2_processes, "test_any_zenoh_subscriber_whose_key_matches_turns_"
                   "forwarding_on")  # fmt: skip
    rule = DOC[DOC.index("## Forwarding") :].split("\n- **ROS → UPS")[0]
    assert "**UPS → ROS only while a Zenoh subscriber matches the topic's key.**" in rule
    assert "exact key" not in rule
    assert "`**`" in rule and "`to_ros` topic of the map" in rule


def _commands(text: str, inline: bool = False) -> list[list[str]]:
    """The commands of ``text``'s sh blocks (with ``inline``: of its inline code that starts
    with ``ups`` and does not end on an option; ```ups status --zenoh``` names one, runs
    none): words as the shell splits them, comments, redirections and ``&`` dropped, ``&&``
    split, each block's own ``NAME=value`` expanded."""
    found: list[list[str]] = []
    if inline:
        spans = [c for c in re.findall(r"`(ups [^`]+)`", text) if not c.split()[-1].startswith("-")]
        blocks = [[span] for span in spans]
    else:
        blocks = [block.splitlines() for block in re.findall(r"```sh\n(.*?)```", text, re.S)]
    for block in blocks:
        names: dict[str, str] = {}

        def expand(word: str, names: dict[str, str] = names) -> str:
            return re.sub(r"\$([A-Z_]+)", lambda m: names[m[1]], word)

        for line in block:
            words: list[str] = []
            skip = False
            for word in [*shlex.split(line, comments=True), "&&"]:
                if skip or re.fullmatch(r"\d?>&?\d*", word):  # > FILE, 2> FILE, 2>&1
                    skip = not skip and not word.endswith(("&1", "&2"))
                elif word in ("&&", "&"):
                    if len(words) == 1 and re.fullmatch(r"[A-Z_]+=.*", words[0]):
                        name, _, value = words[0].partition("=")
                        names[name] = value
                    elif words:
                        found.append([expand(w) for w in words])
                    words = []
                else:
                    words.append(word)
    return found


def _endpoints(argv: list[str]) -> list[str]:
    """The Zenoh endpoints an ``ups`` command line gives (``--ros``, ``--zenoh``, and
    ``--listen``/``--connect`` of ``ups zenoh-router``)."""
    options = {"--ros", "--zenoh"} | ({"--listen", "--connect"} if argv[0] == "zenoh-router"
                                     else set())  # fmt: skip
    return [value for option, value in itertools.pairwise(argv) if option in options]


def test_the_recipe_names_every_part_it_needs() -> None:
    """A router (rmw_zenohd, or ups zenoh-router where it is absent), the CAN-ECB, the extra
    in a checkout, udp_multicast under scripts/netns-run without SocketCAN, and where the
    bridge's counters are seen on CAN."""
    commands = [" ".join(c) for c in _commands(RECIPE) + _commands(RECIPE, inline=True)]
    assert "ros2 run rmw_zenoh_cpp rmw_zenohd" in commands
    assert any(c.startswith("ups zenoh-router --listen") for c in commands)
    assert any(c.startswith("ups can-broker --can") for c in commands)
    assert "scripts/setup" in commands and ".venv/bin/pip install -e .[ros2]" in commands
    assert "scripts/netns-run bash" in commands
    assert any(c.startswith("ups ros2 ") and "--can udp_multicast:" in c for c in commands)
    assert any(c.startswith("ups status --zenoh tcp/") for c in commands)
    assert "CAN-ECB" in RECIPE and "counters" in RECIPE


@pytest.mark.parametrize(
    "argv",
    _commands(DOC) + _commands(RECIPE, inline=True),
    ids=lambda argv: " ".join(argv)[:60].replace(" ", "_"),
)
def test_every_command_of_the_page_is_one_the_cli_takes(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    command, args = argv[0], argv[1:]
    if command in ("source", "export", "ros2"):  # the shell's, and ROS 2's own (not here)
        return
    if command.startswith("scripts/"):
        assert os.access(ROOT / command, os.X_OK), f"no script {command}"
        return
    if command in ("pip", ".venv/bin/pip"):
        found = re.fullmatch(r"(?:ups-pubsub|\.)\[(\w+)\]", args[-1])
        assert args[0] == "install" and found and found[1] in EXTRAS, argv
        return
    assert command == "ups", f"docs/ros2.md runs a command this test does not know: {argv}"
    try:
        _parser(only=args[0]).parse_args(args)
    except SystemExit:
        pytest.fail(f"ups does not take {shlex.join(argv)}: {capsys.readouterr().err}")
    for endpoint in _endpoints(args):
        assert re.fullmatch(r"(tcp|udp|tls|quic)/\S+:\d+", endpoint), (argv, endpoint)
    if args[:2] == ["ros2", "check"]:
        assert main(args) == 0


def test_the_map_and_its_rate_bound_are_the_codes() -> None:
    """Every key the map takes is in the page's example; the rate bound's defaults and limits
    (and the loss credit's window) are the ones ``ros2/_admit.py`` has (issue 41)."""
    from ups.ros2._admit import DEFAULT_BURST, DEFAULT_RATE, LOSS_WINDOW, MAX_BURST, MAX_RATE
    from ups.ros2._mapping import _KEYS, _TOP

    example = DOC[DOC.index("## The map") :].split("```toml\n")[1].split("```")[0]
    keys = {line.split("=")[0].strip() for line in example.splitlines() if "=" in line}
    assert {k.split(".")[0] for k in keys} >= _KEYS | (_TOP - {"topic"})
    assert f"max_rate = {DEFAULT_RATE:g}" in example and f"burst = {DEFAULT_BURST}" in example
    rate = DOC[DOC.index("- **Rate.**") :].split("\n- **")[0]
    assert f"The default, {DEFAULT_RATE:g} a second" in rate
    assert f"a `burst` of {DEFAULT_BURST}" in rate
    assert f"at most {MAX_RATE:,.0f}, `burst` 1 to {MAX_BURST:,}" in rate
    assert f"(at most {LOSS_WINDOW:g} s of them" in DOC


def test_the_security_page_has_the_bridge() -> None:
    """docs/security.md has a row and a section for ``ups ros2`` stating the bound (issue 41:
    the bridge had none)."""
    page = (ROOT / "docs" / "security.md").read_text()
    row = next(line for line in page.splitlines() if line.startswith("| ROS 2 (`ups ros2`) |"))
    assert "`max_rate`" in row and "`ros_lost`" in row
    section = page[page.index("## ROS 2: `ups ros2`") :].split("\n## ")[0]
    assert "`rate_limited`" in section and "`ros_jumps`" in section
    assert "tests/test_ros2_flood.py" in section
