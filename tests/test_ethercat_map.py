"""The EtherCAT map (ethercat/_map.py): examples/robot.ethercat.toml loads as it says, values
pack into the process image and back, and every mistake is refused naming its line
(``ups ethercat check`` exits 2 with it)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ups._catalog import ChannelSpec, Field
from ups._channel import as_channel
from ups.ethercat._map import Entry, MapError, _limits, load_map

from .procs import Proc

EXAMPLES = Path(__file__).parent.parent / "examples"
SPEC = ChannelSpec(as_channel("t/x"), fields=(Field("x", "f64"),))

GOOD = """\
catalog = "robots.toml"
cycle = 0.002

[slave.1]
vendor = 0x2
product = 0x7d23052
outputs = [
  { channel = "robot/brake", field = "brake", byte = 0, type = "u8", safe = 1 },
  { channel = "robot/max-speed", field = "limit", byte = 1, type = "i16", scale = 0.1 },
]
inputs = [{ channel = "robot/distance", field = "distance", byte = 2, type = "u16" }]
"""


def write(tmp_path: Path, text: str) -> Path:
    shutil.copy(EXAMPLES / "robots.toml", tmp_path / "robots.toml")
    path = tmp_path / "map.toml"
    path.write_text(text)
    return path


def test_the_example_map_loads_as_its_comments_say() -> None:
    emap = load_map(EXAMPLES / "robot.ethercat.toml")
    assert (emap.cycle, emap.timeout, emap.status) == (0.002, 0.5, "ethercat/status")
    brake, speed = emap.slaves[1].outputs[0], emap.slaves[2].outputs[0]
    assert brake.safe == b"\x01" and speed.safe == b"\x00\x00"
    assert speed.pack(123) == ((1230).to_bytes(2, "little"), False)  # cm/s -> mm/s
    assert [(c.spec.name, c.every, c.priority) for c in emap.inputs] == [
        ("robot/distance", 0, None), ("robot/speed", 10, 4)]  # fmt: skip


def test_values_saturate_and_say_so(tmp_path: Path) -> None:
    brake, limit = load_map(write(tmp_path, GOOD)).slaves[1].outputs
    assert brake.pack(300) == (b"\xff", True)
    assert brake.pack(-1) == (b"\x00", True)
    assert limit.pack(float("nan")) == (b"\x00\x00", True)
    assert limit.pack(-3276.8) == ((-32768).to_bytes(2, "little", signed=True), False)
    assert limit.unpack(b"\x00" + (-32768).to_bytes(2, "little", signed=True)) == -3276.8


BAD = [
    ("cycle = 0.002", "cycle = 0.0001", 2, "cycle: at least"),
    ('catalog = "robots.toml"', 'catalog = "nope.toml"', 1, "cannot read the catalog"),
    ("product = 0x7d23052", 'product = "x"', 6, "product: a 32-bit number"),
    ("[slave.1]", "[slave.first]", 4, "N is a position"),
    ('field = "brake", byte = 0', 'field = "brakes", byte = 0', 8, "has no field 'brakes'"),
    ('type = "u8"', 'type = "u7"', 8, "type 'u7' is not one of"),
    ("byte = 1,", "byte = 0,", 9, "byte 0 is written by line 8 too"),
    ("safe = 1", "safe = 256", 8, "safe 256 does not fit a u8"),
    ("scale = 0.1", "scale = 0", 9, "scale is a finite number other than 0"),
    ('"robot/distance"', '"robot/nope"', 11, "has no fixed payload layout"),
    ('type = "u16" }', 'type = "u16", publish = "sometimes" }', 11, 'publish is "change"'),
    ('type = "u16" }', 'type = "u16", every = 3 }', 11, 'every K goes with publish = "every"'),
    ("vendor = 0x2\n", "", 4, "no vendor"),
    ("cycle = 0.002", "cycles = 0.002", 2, "unknown key 'cycles'"),
    # values the master cannot run with (issue 41): each refused by check, with its line
    ("cycle = 0.002", "cycle = inf", 2, "cycle: seconds, a number above 0 and at most 1"),
    ("cycle = 0.002", "cycle = 1e308", 2, "cycle: seconds, a number above 0 and at most 1"),
    ("cycle = 0.002", "cycle = 3600000", 2, "cycle: seconds, a number above 0 and at most 1"),
    ("cycle = 0.002", "cycle = nan", 2, "cycle: seconds, a number above 0 and at most 1"),
    ("cycle = 0.002", "cycle = 0.002\ntimeout = inf", 3, "timeout: seconds, a number above 0"),
    (
        'type = "u16" }',
        'type = "u16", publish = "every", every = 99999999999999999999 }',
        11,
        "every is at most 1000000 cycles",
    ),
    (
        'type = "u16" }',
        'type = "u16", publish = "every", every = 9999999 }',
        11,
        "every is at most 1000000 cycles",
    ),
]


@pytest.mark.parametrize(("old", "new", "line", "says"), BAD)
def test_a_mistake_is_refused_naming_its_line(
    tmp_path: Path, old: str, new: str, line: int, says: str
) -> None:
    assert old in GOOD
    path = write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(MapError) as refused:
        load_map(path)
    assert str(refused.value).startswith(f"{path}:{line}:"), refused.value
    assert says in str(refused.value)


def test_an_input_channel_needs_every_field(tmp_path: Path) -> None:
    text = GOOD.replace('"robot/distance", field = "distance"', '"robot/local-pose", field = "x"')
    with pytest.raises(MapError, match=r":11: .*field 'y' of robot/local-pose comes from no input"):
        load_map(write(tmp_path, text))


def test_check_prints_the_map_or_exits_2_naming_the_line(tmp_path: Path) -> None:
    code, out = Proc("ethercat", "check", str(EXAMPLES / "robot.ethercat.toml")).finish(30)
    assert code == 0, out
    assert "slave 2: vendor 0x000005a5 product 0x00001234" in out
    assert "slave 2 input byte 0 (i16) -> robot/speed.speed, every 10 cycle(s)" in out
    path = write(tmp_path, GOOD.replace('type = "u8"', 'type = "u7"'))
    bad = Proc("ethercat", "check", str(path))
    assert bad.finish(30)[0] == 2
    assert bad.stderr_lines[-1].startswith(f"ups ethercat: {path}:8: [slave.1] outputs[0]")


def test_the_status_channel_in_the_catalog_is_what_ups_ethercat_publishes() -> None:
    from ups import name_to_uid
    from ups._catalog import Catalog
    from ups.ethercat._bridge import STATUS_FIELDS, STATUS_LAYOUT

    spec = Catalog.load(EXAMPLES / "robots.toml").get(name_to_uid("ethercat/status"))
    assert spec is not None and spec.size == STATUS_LAYOUT.size
    values = dict(zip(STATUS_FIELDS, range(1, 12), strict=True))
    decoded = spec.decode(STATUS_LAYOUT.pack(*values.values()))
    assert decoded == {**values, "reserved": 0}


@settings(max_examples=300, deadline=None)
@given(
    kind=st.sampled_from(["u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64"]),
    scale=st.sampled_from([1.0, 0.1, 0.001, 2.5, -1.0]),
    offset=st.sampled_from([0.0, -40.0, 1000.0]),
    value=st.floats(allow_nan=True, allow_infinity=True, width=64),
)
def test_a_value_packs_to_the_nearest_raw_in_range_or_says_it_was_clipped(
    kind: str, scale: float, offset: float, value: float
) -> None:
    """The invariant of every output: the bytes are the type's width; unpacked they give the
    value to within half a step of the scale, unless the value did not fit (clipped): then
    they hold the nearest end of the range (NaN: 0)."""
    entry = Entry(1, SPEC, "x", 0, kind, scale, offset, 1)
    raw, clipped = entry.pack(value)
    assert len(raw) == entry.size
    back = entry.unpack(raw)
    if not clipped:
        assert math.isfinite(value)
        assert abs(back - value) <= abs(scale) / 2 * (1 + 1e-9) + 1e-9 * abs(value)
    elif math.isnan(value):
        assert back == offset
    else:
        low, high = _limits(kind)
        end = high if (value - offset) / scale > 0 else low
        assert back == end * scale + offset


def test_a_cycles_working_counter_is_judged_as_docs_ethercat_says() -> None:
    """No frame back (pysoem: EC_NOFRAME, -1) is a lost frame; any other wrong count, 0 too
    (an answer no slave counted), is a working counter error (it was counted lost)."""
    from ups.ethercat._cycle import judge

    assert judge(3, 3) is None
    assert judge(-1, 3) == "lost"
    assert judge(0, 3) == "wkc_errors"
    assert judge(2, 3) == judge(4, 3) == "wkc_errors"
