from __future__ import annotations

import hashlib

import pytest

from ups import Channel, ConfigError, name_to_uid, parse_channel
from ups._channel import as_channel


def test_name_hash_is_the_documented_one() -> None:
    digest = hashlib.sha256(b"robot/speed").digest()
    assert name_to_uid("robot/speed") == int.from_bytes(digest[:8], "big")
    assert name_to_uid("robot/speed") == 0xEB79DAB9BBB48DC7  # pinned: the hash must never change


def test_parse_channel() -> None:
    assert parse_channel("0x10") == Channel(0x10)
    assert parse_channel("0XfF") == Channel(0xFF)
    assert parse_channel("robot/speed") == Channel(name_to_uid("robot/speed"), "robot/speed")


@pytest.mark.parametrize("bad", ["", "0x", "0xZZ", "0x1" + "0" * 16, "a\nb", "x" * 256])
def test_bad_channels_are_config_errors(bad: str) -> None:
    with pytest.raises(ConfigError):
        parse_channel(bad)


@pytest.mark.parametrize("bad", [-1, 1 << 64, True, 1.5, None])
def test_bad_uids_are_config_errors(bad: object) -> None:
    with pytest.raises(ConfigError):
        as_channel(bad)  # type: ignore[arg-type]
