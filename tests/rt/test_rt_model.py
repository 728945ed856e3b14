"""Message specifications and the CSV loader."""

from __future__ import annotations

import dataclasses
from fractions import Fraction
from pathlib import Path

import pytest

from ups.rt import MessageSpec, NotSchedulable, load_csv

F = Fraction


def test_floats_are_taken_at_their_decimal_value() -> None:
    spec = MessageSpec("a", 1, period_ms=0.1, deadline_ms=0.3, jitter_ms=0.2)
    assert (spec.period_ms, spec.deadline_ms, spec.jitter_ms) == (F(1, 10), F(3, 10), F(1, 5))
    assert MessageSpec("a", 1, 5, 5) == MessageSpec("a", 1, F(5), 5.0, 0)
    assert dataclasses.replace(spec, priority=3).priority == 3
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.name = "b"  # type: ignore[misc]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"name": ""}, "name"),
        ({"size_bytes": 65}, "size_bytes"),
        ({"size_bytes": 1.5}, "size_bytes"),
        ({"period_ms": 0}, "period_ms must be positive"),
        ({"deadline_ms": -1}, "deadline_ms must be positive"),
        ({"jitter_ms": -0.1}, "jitter_ms must not be negative"),
        ({"period_ms": float("nan")}, "finite"),
        ({"priority": -1}, "priority"),
    ],
)
def test_invalid_specs(kwargs: dict[str, object], match: str) -> None:
    arguments: dict[str, object] = {
        "name": "m",
        "size_bytes": 1,
        "period_ms": 10,
        "deadline_ms": 10,
    }
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        MessageSpec(**arguments)  # type: ignore[arg-type]


def test_load_csv_skips_comments_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "set.csv"
    path.write_text(
        "\ufeff# a comment\n\nid, size_bytes, period_ms, deadline_ms, jitter_ms\n"
        "# another\nbrake, 2, 5, 4.5, 0.25\n\nwipers,1,100,100,0\n",
        encoding="utf-8",
    )
    assert load_csv(path) == [
        MessageSpec("brake", 2, F(5), F("4.5"), F("0.25")),
        MessageSpec("wipers", 1, F(100), F(100), F(0)),
    ]


def test_load_csv_errors_name_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "set.csv"
    path.write_text("name,size_bytes,jitter_ms,period_ms,deadline_ms\na,1,0,5,5\nb,1,0,0,5\n")
    with pytest.raises(ValueError, match=r"set\.csv:3: message 'b': period_ms must be positive"):
        load_csv(path)
    with pytest.raises(OSError):
        load_csv(tmp_path / "absent.csv")


def test_not_schedulable_message() -> None:
    error = NotSchedulable("brake", F("4.25"), F(4), "with given priorities")
    assert isinstance(error, ValueError)
    assert error.channel == "brake"
    assert str(error) == (
        "message 'brake' would miss its deadline: worst-case response time 4.25 ms > "
        "deadline 4 ms; with given priorities"
    )
    assert "unbounded" in str(NotSchedulable("x", None, F(1)))
