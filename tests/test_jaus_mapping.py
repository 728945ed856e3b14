"""The JAUS mapping file: checked once at start, every problem named by file and line, and the
shipped demo mapping converts as it says."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ups._catalog import Catalog
from ups.jaus import (
    ReportAuthority,
    ReportGlobalPose,
    SetWrenchEffort,
    TimeStamp,
    encode_payload,
)
from ups.jaus._mapping import MappingError, load_mapping

from .procs import ROOT, Proc

CATALOG = """
[channel."robot/max-speed"]
byte_order = "big"
fields = [{ name = "limit", type = "i16", unit = "cm/s" }]

[channel."robot/pose"]
fields = [{ name = "lat", type = "f64" }, { name = "lon", type = "f64" },
          { name = "heading", type = "f32" }]

[channel."robot/raw"]

[channel."robot/level"]
fields = [{ name = "level", type = "u8" }]
"""

GOOD = """catalog = "catalog.toml"

[message.SetWrenchEffort]
channel = "robot/max-speed"
fields.propulsive_linear_x = { field = "limit", scale = 2.0 }

[message.ReportGlobalPose]
channel = "robot/pose"
rate = 10
fields.latitude = "lat"
fields.longitude = { field = "lon" }
fields.yaw = { field = "heading", scale = 57.29577951308232 }
constants = { altitude = 0 }
ignore = ["position_rms", "roll", "pitch", "attitude_rms", "timestamp"]
"""


def write(tmp_path: Path, text: str) -> Path:
    (tmp_path / "catalog.toml").write_text(CATALOG)
    path = tmp_path / "map.toml"
    path.write_text(text)
    return path


def test_the_demo_robots_mapping_checks_and_converts() -> None:
    bridge = load_mapping(ROOT / "examples" / "robot.jaus.toml")
    effort = bridge["SetWrenchEffort"]
    assert effort.command
    data = effort.to_ups(SetWrenchEffort(propulsive_linear_x=50.0))
    assert effort.channel.decode(data) == {"limit": 100}  # 50 % of full: 100 cm/s


def test_a_report_is_made_from_the_channels_event(tmp_path: Path) -> None:
    bridge = load_mapping(write(tmp_path, GOOD))
    pose = bridge["ReportGlobalPose"]
    assert not pose.command and pose.rate == 10.0
    event = pose.channel.encode({"lat": 48.4, "lon": 9.95, "heading": 1.5})
    report = pose.from_ups(event)
    assert isinstance(report, ReportGlobalPose)
    assert (report.latitude, report.longitude, report.altitude) == (48.4, 9.95, 0)
    assert report.yaw == pytest.approx(1.5 / 57.29577951308232)


@given(st.integers(0, 255))
def test_a_report_into_an_integer_field_is_an_integer_on_the_wire(level: int) -> None:
    """Report Authority's field is a u8: the scaled value is rounded to one, so the report
    encodes (it used to be a float, and every answer and Event on it failed)."""
    body = 'catalog = "catalog.toml"\n[message.ReportAuthority]\nchannel = "robot/level"\n'
    body += 'fields.authority = { field = "level", scale = 2.0, offset = 1.0 }\n'
    with tempfile.TemporaryDirectory() as tmp:
        entry = load_mapping(write(Path(tmp), body))["ReportAuthority"]
    report = entry.from_ups(entry.channel.encode({"level": level}))
    assert report == ReportAuthority(round((level - 1.0) / 2.0))
    assert isinstance(report.authority, int)
    assert encode_payload(report)[1] == bytes([report.authority])


@given(st.floats(-100, 100))
def test_commands_convert_with_the_scale(effort: float) -> None:
    bridge = load_mapping(ROOT / "examples" / "robot.jaus.toml")
    entry = bridge["SetWrenchEffort"]
    limit = entry.channel.decode(entry.to_ups(SetWrenchEffort(propulsive_linear_x=effort)))
    assert abs(limit["limit"] - effort * 2.0) <= 1  # an i16 of cm/s


BAD = [
    ("[message.SetWrenchEfort]\nchannel = 'robot/max-speed'\n", 3, "unknown JAUS message"),
    ("[message.SetWrenchEffort]\nchannel = 'robot/nope'\n", 4, "has no payload layout"),
    ("[message.SetWrenchEffort]\nchannel = 'robot/raw'\n", 4, "has no payload layout"),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\nfields.thrust = 'limit'\n",
        5,
        "has no field 'thrust'",
    ),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\n\nfields.propulsive_linear_x"
        " = 'speed'\n",
        6,
        "has no field 'speed'",
    ),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\n",
        3,
        "field 'limit' of robot/max-speed is neither mapped, constant",
    ),
    (
        "[message.ReportGlobalPose]\nchannel = 'robot/pose'\nfields.latitude = 'lat'\n",
        3,
        "is neither mapped, constant nor ignored",
    ),
    (
        "[message.ReportIdentification]\nchannel = 'robot/pose'\nfields.identification = 'lat'\n",
        5,
        "type mismatch: ReportIdentification.identification (text)",
    ),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\nrate = -1\n"
        "fields.propulsive_linear_x = 'limit'\n",
        5,
        "rate must be",
    ),
    ("[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\nspeed = 3\n", 5, "unknown key"),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\n"
        "fields.propulsive_linear_x = { field = 'limit', scale = 0 }\n",
        5,
        "scale 0",
    ),
    (
        "[message.ReportAuthority]\nchannel = 'robot/level'\nconstants = { authority = 2.5 }\n",
        5,
        "is an integer, not 2.5",
    ),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\ntimestamp = 'event'\n"
        "fields.propulsive_linear_x = 'limit'\n",
        5,
        "only a report with a time stamp",
    ),
    (
        "[message.ReportGlobalPose]\nchannel = 'robot/pose'\nfields.latitude = 'lat'\n"
        "timestamp = 'now'\n",
        6,
        'timestamp = "event"',
    ),
    (
        "[message.ReportGlobalPose]\nchannel = 'robot/pose'\nfields.latitude = 'lat'\n"
        "timestamp = 'event'\nignore = ['longitude', 'altitude', 'position_rms', 'roll', "
        "'pitch', 'yaw', 'attitude_rms', 'timestamp']\n",
        6,
        "neither constant nor ignored",
    ),
]

COMMAND = (
    "\n[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\n"
    "fields.propulsive_linear_x = 'limit'\n"
)
BAD += [
    ('[authority]\n"10.0.0.0/8" = 5\n"10.0.0.1/8" = 5\n' + COMMAND, 5, "not an address range"),
    ('[authority]\n"10.0.0.0/8" = 5\n"::/0" = 300\n' + COMMAND, 5, "an authority is 0-255"),
    ('[authority]\n"fd00::/8" = true\n' + COMMAND, 4, "an authority is 0-255, not True"),
    ("authority = 5\n" + COMMAND, 3, "give address ranges"),
    ("[authority]\n" + COMMAND, 3, "give address ranges"),
    # values ups jaus cannot run with (issue 41)
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\nrate = inf\n"
        "fields.propulsive_linear_x = 'limit'\n",
        5,
        "rate must be a number of reports per second above 0, at most 1000",
    ),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\nrate = 1e9\n"
        "fields.propulsive_linear_x = 'limit'\n",
        5,
        "at most 1000",
    ),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\n"
        "fields.propulsive_linear_x = { field = 'limit', scale = inf }\n",
        5,
        "scale and offset are finite numbers",
    ),
    (
        "[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\n"
        "fields.propulsive_linear_x = { field = 'limit', offset = nan }\n",
        5,
        "scale and offset are finite numbers",
    ),
    (
        "[message.ReportAuthority]\nchannel = 'robot/level'\nconstants = { authority = inf }\n",
        5,
        "constant 'authority' must be a finite number",
    ),
]


def test_the_authority_table_caps_per_address_range(tmp_path: Path) -> None:
    import ipaddress

    body = GOOD + '\n[authority]\n"127.0.0.0/8" = 255\n"192.168.1.0/24" = 100\n'
    caps = load_mapping(write(tmp_path, body)).authority
    assert caps is not None and caps.cap("192.168.1.7") == (
        ipaddress.ip_network("192.168.1.0/24"),
        100,
    )
    assert load_mapping(write(tmp_path, GOOD)).authority is None  # no table: no caps


def test_a_report_can_be_stamped_with_its_events_arrival(tmp_path: Path) -> None:
    body = GOOD.replace('"attitude_rms", "timestamp"]', '"attitude_rms"]\ntimestamp = "event"')
    pose = load_mapping(write(tmp_path, body))["ReportGlobalPose"]
    event = pose.channel.encode({"lat": 48.4, "lon": 9.95, "heading": 0.0})
    when = 1_700_000_000.25  # 2023-11-14 22:13:20.250 UTC
    report = pose.from_ups(event, when)
    assert report.timestamp == TimeStamp(day=14, hour=22, minute=13, second=20, millisecond=250)
    assert pose.from_ups(event).timestamp is None  # no time given: none made up
    _, data = encode_payload(report)
    assert int.from_bytes(data[:2], "little") >> 8 & 1  # presence bit 8: the time stamp


@pytest.mark.parametrize(("body", "line", "says"), BAD)
def test_every_problem_is_named_with_its_line(
    tmp_path: Path, body: str, line: int, says: str
) -> None:
    path = write(tmp_path, f'catalog = "catalog.toml"\n\n{body}')
    with pytest.raises(MappingError) as caught:
        load_mapping(path)
    assert str(caught.value).startswith(f"{path}:{line}: ")
    assert says in str(caught.value)


def test_a_broken_file_or_catalog_is_named(tmp_path: Path) -> None:
    path = write(tmp_path, "[message.SetWrenchEffort\n")
    with pytest.raises(MappingError, match=r"map\.toml"):
        load_mapping(path)
    path.write_text("[message.SetWrenchEffort]\nchannel = 'robot/max-speed'\n")
    with pytest.raises(MappingError, match="no catalog"):
        load_mapping(path)
    assert load_mapping(write(tmp_path, GOOD), Catalog.from_text(CATALOG))


def test_ups_jaus_check(tmp_path: Path) -> None:
    ok = Proc("jaus", "check", str(ROOT / "examples" / "robot.jaus.toml"))
    code, out = ok.finish()
    assert code == 0 and "SetWrenchEffort: JAUS -> UPS on robot/max-speed" in out
    bad = Proc("jaus", "check", str(write(tmp_path, BAD[0][0])))
    code, _ = bad.finish()
    assert code == 2 and len(bad.stderr_lines) == 1
    assert f"{tmp_path / 'map.toml'}:1: " in bad.stderr_lines[0]
