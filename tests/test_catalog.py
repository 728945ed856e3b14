"""The channel catalog: layouts decode what they encode, and a bad file says where it is bad."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ups import ConfigError, DecodeError, name_to_uid
from ups._catalog import Catalog, load_catalog

GOOD = """\
[channel."robot/speed"]
description = "wheel speeds"
period = 0.01
priority = 0x40
fields = [
    { name = "left", type = "i16", scale = 0.001, unit = "m/s" },
    { name = "right", type = "i16", scale = 0.001, unit = "m/s" },
]

[channel."robot/status"]
byte_order = "big"
fields = [{ name = "code", type = "u32" }, { name = "ok", type = "bool" },
          { name = "text", type = "str" }]
realtime = { period = 0.02, deadline = 0.01 }

[channel."0x0000000000001234"]
"""


def test_a_catalog_names_and_decodes(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text(GOOD)
    catalog = Catalog.load(path)
    assert len(catalog) == 3
    speed = catalog.get(name_to_uid("robot/speed"))
    assert speed is not None and speed.priority == 0x40 and speed.period == 0.01
    assert speed.size == 4
    assert catalog.format(speed.uid, bytes.fromhex("e803d007")) == "left=1 m/s right=2 m/s"
    assert catalog.decode(speed.uid, b"\x01") is None  # too short: not its layout
    assert "does not fit" in catalog.format(speed.uid, b"\x01")
    status = catalog.get(name_to_uid("robot/status"))
    assert status is not None and status.realtime is not None
    assert status.realtime.deadline == 0.01 and status.size is None
    data = status.encode({"code": 7, "ok": True, "text": "hi"})
    assert data == b"\x00\x00\x00\x07\x01hi"
    assert status.decode(data) == {"code": 7, "ok": True, "text": "hi"}
    assert catalog.channel(0x1234).name is None and catalog.format(0x1234, b"\xab") == "ab"
    assert catalog.format(0x999, b"") == "-"  # unknown channel: hex


@given(
    left=st.integers(-32768, 32767),
    right=st.integers(-32768, 32767),
    x=st.floats(allow_nan=False, allow_infinity=False, width=32),
)
def test_encode_then_decode_is_the_identity(left: int, right: int, x: float) -> None:
    doc = {"left": left / 1000, "right": right / 1000, "x": x}
    catalog = Catalog.from_text(
        '[channel."c"]\nfields = [{ name = "left", type = "i16", scale = 0.001 },'
        '{ name = "right", type = "i16", scale = 0.001 }, { name = "x", type = "f32" }]\n'
    )
    (spec,) = catalog
    values = spec.decode(spec.encode(doc))
    assert round(float(values["left"]) * 1000) == left
    assert round(float(values["right"]) * 1000) == right
    assert values["x"] == x


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ('[channel."a"]\nfields = [{ name = "v", type = "u7" }]\n', "type must be one of"),
        (
            '[channel."a"]\nfields = [{ name = "s", type = "str" }, { name = "v", type = "u8" }]\n',
            "only the last field",
        ),
        ('[channel."a"]\npriority = 300\n', "priority must be an integer 2..255"),
        ('[channel."a"]\npriority = 1\n', "priority must be an integer 2..255"),
        ('[channel."a"]\nperiod = -1\n', "period must be a finite number of seconds above 0"),
        ('[channel."a"]\nperiod = inf\n', "period must be a finite number"),
        ('[channel."a"]\ndescription = 3\n', "description must be a string"),
        ('[channel."a"]\nfields = [{ name = "v", type = "u8", unit = 3 }]\n', "unit must be a"),
        ('[channel."0x_1"]\n', "bad channel UID"),
        ('[channel."a"]\ncolour = "red"\n', "unknown key colour"),
        ('[channel."a"]\nrealtime = { deadline = 0.1 }\n', "realtime needs a period"),
        ('[channel."0xzz"]\n', "bad channel UID"),
        ('[channel."a"]\nfields = [{ name = "v", type = "u8", scale = 0 }]\n', "scale must not"),
        ("[nodes]\n", "unknown table nodes"),
        ("[channel\n", "catalog"),
    ],
)
def test_a_bad_catalog_names_the_channel_and_what_is_wrong(text: str, says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        Catalog.from_text(text)


def test_a_missing_catalog_file_and_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with pytest.raises(ConfigError, match="cannot read the catalog"):
        Catalog.load(tmp_path / "nope.toml")
    monkeypatch.delenv("UPS_CATALOG", raising=False)
    assert len(load_catalog(None)) == 0
    path = tmp_path / "c.toml"
    path.write_text(GOOD)
    monkeypatch.setenv("UPS_CATALOG", str(path))
    assert len(load_catalog(None)) == 3


def test_decode_refuses_a_payload_of_another_size() -> None:
    (spec,) = Catalog.from_text('[channel."a"]\nfields = [{ name = "v", type = "u16" }]\n')
    with pytest.raises(DecodeError, match="the layout needs 2"):
        spec.decode(b"\x01\x02\x03")
    with pytest.raises(ConfigError, match="a value for v is missing"):
        spec.encode({})
    with pytest.raises(ConfigError, match="v=70000"):
        spec.encode({"v": 70000})


def test_ups_pub_encodes_field_values_with_the_catalog() -> None:
    from .procs import ROOT, Proc, start_tcp_broker

    catalog = str(ROOT / "examples" / "robots.toml")
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("sub", "robot/max-speed", "--broker", address, "--count", "1",
                      "--json", "--timeout", "20") as sub:  # fmt: skip
        sub.wait_for_line("subscribed to")
        pub = Proc("pub", "robot/max-speed", "limit=30", "--broker", address, "--catalog", catalog)
        assert pub.finish()[0] == 0, pub.stderr_lines
        code, out = sub.finish()
        assert code == 0 and '"data": "001e"' in out
    bad = Proc("pub", "robot/max-speed", "speed=30", "--broker", address, "--catalog", catalog)
    assert bad.finish()[0] == 2
    assert bad.stderr_lines == ["ups pub: robot/max-speed has no field speed\n"]


def test_integers_encode_exactly_and_bad_values_are_config_errors() -> None:
    (spec,) = Catalog.from_text(
        '[channel."a"]\nfields = [{ name = "u", type = "u64" }, { name = "b", type = "bytes" }]\n'
    )
    top = (1 << 64) - 1
    assert spec.decode(spec.encode({"u": str(top), "b": "ab"})) == {"u": top, "b": b"\xab"}
    assert spec.decode(spec.encode({"u": "9007199254740993", "b": ""}))["u"] == 9007199254740993
    assert spec.decode(spec.encode({"u": "0x10", "b": ""}))["u"] == 16
    with pytest.raises(ConfigError, match="b='zz'"):
        spec.encode({"u": 1, "b": "zz"})
    with pytest.raises(ConfigError, match="u='-1'"):
        spec.encode({"u": "-1", "b": ""})
    (rt,) = Catalog.from_text('[channel."r"]\nfields = [{ name = "x", type = "u8" }]\n'
                              "realtime = { period = 0.01, jitter = 0 }\n")  # fmt: skip
    assert rt.realtime is not None and rt.realtime.jitter == 0.0
