"""Message specifications, results, errors and the CSV loader of the real-time analysis."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

Number = Fraction | float
"""A time in milliseconds. Floats are read through their shortest decimal form (``0.1`` is
exactly one tenth), so values typed by a person are analysed exactly."""


def _exact(value: Number | str) -> Fraction:
    """Convert a time or a decimal string to an exact fraction (floats via their repr)."""
    if isinstance(value, Fraction):
        return value
    if isinstance(value, bool):
        raise TypeError("a boolean is not a time")
    if isinstance(value, int):
        return Fraction(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{value!r} is not a finite number")
        return Fraction(repr(value))
    if isinstance(value, str):
        text = value.strip()
        try:
            result = Fraction(text)
        except (ValueError, ZeroDivisionError):
            raise ValueError(f"{value!r} is not a number") from None
        return result
    raise TypeError(f"{value!r} is not a number")


@dataclass(frozen=True)
class MessageSpec:
    """One periodic (or sporadic, with ``period_ms`` its minimum inter-arrival time) CAN message.

    ``jitter_ms`` is the queuing jitter: the longest time from the nominal release of an instance
    until it is queued for transmission. ``priority`` is optional; when one message of a set has
    it, all must, and lower values are higher priorities (as in CAN arbitration). When no message
    has it, the order of the sequence is the priority order, highest first. Times are exact
    fractions after construction; floats are taken at their shortest decimal form.

    ``frames`` > 1 makes each instance a transfer of that many frames of ``size_bytes`` each
    (a UPS event larger than one frame), queued together at the message's priority.
    """

    name: str
    size_bytes: int
    period_ms: Fraction
    deadline_ms: Fraction
    jitter_ms: Fraction = Fraction(0)
    priority: int | None = None
    frames: int = 1

    def __init__(
        self,
        name: str,
        size_bytes: int,
        period_ms: Number,
        deadline_ms: Number,
        jitter_ms: Number = 0,
        priority: int | None = None,
        frames: int = 1,
    ) -> None:
        if not isinstance(name, str) or not name:
            raise ValueError("a message needs a non-empty name")
        if isinstance(size_bytes, bool) or not isinstance(size_bytes, int):
            raise ValueError(f"message {name!r}: size_bytes must be an integer")
        if not 0 <= size_bytes <= 64:
            raise ValueError(f"message {name!r}: size_bytes must be 0..64, not {size_bytes}")
        period = _exact(period_ms)
        deadline = _exact(deadline_ms)
        jitter = _exact(jitter_ms)
        if period <= 0:
            raise ValueError(f"message {name!r}: period_ms must be positive, not {period_ms}")
        if deadline <= 0:
            raise ValueError(f"message {name!r}: deadline_ms must be positive, not {deadline_ms}")
        if jitter < 0:
            raise ValueError(f"message {name!r}: jitter_ms must not be negative, not {jitter_ms}")
        if priority is not None and (
            isinstance(priority, bool) or not isinstance(priority, int) or priority < 0
        ):
            raise ValueError(f"message {name!r}: priority must be a non-negative integer")
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "size_bytes", size_bytes)
        object.__setattr__(self, "period_ms", period)
        object.__setattr__(self, "deadline_ms", deadline)
        object.__setattr__(self, "jitter_ms", jitter)
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            raise ValueError(f"message {name!r}: frames must be a positive integer, not {frames}")
        object.__setattr__(self, "priority", priority)
        object.__setattr__(self, "frames", frames)


@dataclass(frozen=True)
class Result:
    """The analysed worst-case response time of one message.

    ``response_time_ms`` is measured from the nominal release (so it includes queuing jitter
    when the method counts it) to the end of the frame's interframe space; it is ``None`` when
    the level-m busy period does not converge (bus utilisation at that priority level >= 1). It
    is reported even when it exceeds the deadline. ``schedulable`` is ``response_time_ms <=
    deadline_ms``.
    """

    name: str
    response_time_ms: Fraction | None
    deadline_ms: Fraction
    schedulable: bool


class NotSchedulable(ValueError):
    """A message set cannot meet its deadlines; ``channel`` names the message that would miss.

    ``response_time_ms`` is that message's analysed response time (``None`` when unbounded) and
    ``deadline_ms`` its deadline.
    """

    def __init__(
        self,
        channel: str,
        response_time_ms: Fraction | None,
        deadline_ms: Fraction,
        detail: str = "",
    ) -> None:
        self.channel = channel
        self.response_time_ms = response_time_ms
        self.deadline_ms = deadline_ms
        shown = "unbounded" if response_time_ms is None else f"{_ms(response_time_ms)} ms"
        text = (
            f"message {channel!r} would miss its deadline: worst-case response time {shown} "
            f"> deadline {_ms(deadline_ms)} ms"
        )
        super().__init__(f"{text}{'; ' + detail if detail else ''}")


def _ms(value: Fraction) -> str:
    """Format a time in ms for people: up to 6 decimals, no trailing zeros."""
    text = f"{float(value):.6f}".rstrip("0").rstrip(".")
    return text or "0"


def _ordered(specs: Sequence[MessageSpec]) -> list[MessageSpec]:
    """Return ``specs`` highest priority first, checking names and priorities.

    Without ``priority`` fields the sequence order is kept; with them, lower value first.
    Raises ``ValueError`` for duplicate names, duplicate priorities or a mix of both styles.
    """
    names: set[str] = set()
    for spec in specs:
        if spec.name in names:
            raise ValueError(f"message name {spec.name!r} is used twice")
        names.add(spec.name)
    given = [spec.priority is not None for spec in specs]
    if not any(given):
        return list(specs)
    if not all(given):
        missing = next(spec.name for spec in specs if spec.priority is None)
        raise ValueError(f"message {missing!r} has no priority while others have one")
    seen: dict[int, str] = {}
    for spec in specs:
        assert spec.priority is not None
        if spec.priority in seen:
            raise ValueError(
                f"priority {spec.priority} is given to both {seen[spec.priority]!r} "
                f"and {spec.name!r}"
            )
        seen[spec.priority] = spec.name
    return sorted(specs, key=lambda spec: spec.priority if spec.priority is not None else 0)


_REQUIRED = ("size_bytes", "jitter_ms", "period_ms", "deadline_ms")


def load_csv(path: str | Path) -> list[MessageSpec]:
    """Read a message set from a CSV file.

    The first column names each message; columns ``size_bytes``, ``jitter_ms``, ``period_ms`` and
    ``deadline_ms`` are required, ``priority`` is optional (lower value = higher priority; without
    it the rows are in priority order, highest first). Lines starting with ``#`` and blank lines
    are skipped. Raises ``OSError`` when the file cannot be read and ``ValueError`` with the file
    name and line number for anything malformed.
    """
    source = Path(path)
    with source.open(newline="", encoding="utf-8-sig") as handle:
        lines = [
            (number, line)
            for number, line in enumerate(handle, start=1)
            if line.strip() and not line.lstrip().startswith("#")
        ]
    if not lines:
        raise ValueError(f"{source}: no header line")
    rows = list(csv.reader([line for _, line in lines]))
    header = [cell.strip() for cell in rows[0]]
    if not header or not header[0]:
        raise ValueError(f"{source}:{lines[0][0]}: the first column must name the messages")
    missing = [column for column in _REQUIRED if column not in header]
    if missing:
        raise ValueError(f"{source}:{lines[0][0]}: missing column(s) {', '.join(missing)}")
    index = {column: header.index(column) for column in header}
    has_priority = "priority" in index
    specs: list[MessageSpec] = []
    for (number, _), row in zip(lines[1:], rows[1:], strict=True):
        where = f"{source}:{number}"
        cells = [cell.strip() for cell in row]
        if len(cells) < len(header):
            raise ValueError(f"{where}: expected {len(header)} columns, found {len(cells)}")

        def cell(column: str, cells: list[str] = cells, where: str = where) -> str:
            text = cells[index[column]]
            if not text:
                raise ValueError(f"{where}: empty {column}")
            return text

        name = cells[0]
        if not name:
            raise ValueError(f"{where}: empty message name")
        try:
            size = int(cell("size_bytes"))
        except ValueError as error:
            if "empty" in str(error):
                raise
            raise ValueError(
                f"{where}: size_bytes {cells[index['size_bytes']]!r} is not an integer"
            ) from None
        times: dict[str, Fraction] = {}
        for column in ("jitter_ms", "period_ms", "deadline_ms"):
            text = cell(column)
            try:
                times[column] = _exact(text)
            except ValueError:
                raise ValueError(f"{where}: {column} {text!r} is not a number") from None
        priority: int | None = None
        if has_priority:
            text = cell("priority")
            try:
                priority = int(text)
            except ValueError:
                raise ValueError(f"{where}: priority {text!r} is not an integer") from None
        try:
            specs.append(
                MessageSpec(
                    name,
                    size,
                    period_ms=times["period_ms"],
                    deadline_ms=times["deadline_ms"],
                    jitter_ms=times["jitter_ms"],
                    priority=priority,
                )
            )
        except ValueError as error:
            raise ValueError(f"{where}: {error}") from None
    if not specs:
        raise ValueError(f"{source}: no messages")
    try:
        _ordered(specs)
    except ValueError as error:
        raise ValueError(f"{source}: {error}") from None
    return specs
