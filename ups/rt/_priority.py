"""Priority assignment for CAN messages and its mapping onto the UPS 8-bit priority field."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from fractions import Fraction
from typing import Literal

from ._analysis import Blocking, Method, _blocking, _Msg, _prepare, _response_time, analyze
from ._model import MessageSpec, NotSchedulable, _ordered

Policy = Literal["audsley", "deadline-monotonic", "given"]
POLICIES: tuple[Policy, ...] = ("audsley", "deadline-monotonic", "given")


def _ranked(order: Sequence[MessageSpec]) -> list[MessageSpec]:
    return [dataclasses.replace(spec, priority=rank) for rank, spec in enumerate(order)]


def deadline_monotonic(specs: Sequence[MessageSpec]) -> list[MessageSpec]:
    """Order ``specs`` by deadline, shortest first (ties keep their input order).

    Returns copies, highest priority first, whose ``priority`` is their rank (0 = highest).
    Any ``priority`` already in ``specs`` is ignored.
    """
    _ordered([dataclasses.replace(spec, priority=None) for spec in specs])  # unique names
    return _ranked(sorted(specs, key=lambda spec: spec.deadline_ms))


def audsley(
    specs: Sequence[MessageSpec],
    bitrate: int,
    id_bits: int = 29,
    *,
    method: Method = "davis2007",
    blocking: Blocking = "max-frame",
    fd: bool = False,
) -> list[MessageSpec]:
    """Audsley's optimal priority assignment, with the response-time test of ``method``.

    From the lowest priority level up, the level goes to a message that meets its deadline there
    with all still unplaced messages above it (those with the longest deadlines are tried first).
    The tests of ``analyze`` depend only on which messages are above and below, not on their
    order, so this finds a schedulable ordering whenever one exists (Davis et al. 2007).
    Returns copies, highest priority first, whose ``priority`` is their rank (0 = highest); any
    ``priority`` in ``specs`` is ignored.

    Raises ``NotSchedulable`` when no ordering meets every deadline. It names, among the
    messages none of which fits the level where the search stopped, the one that misses by the
    least; the message lists the others.
    """
    plain = [dataclasses.replace(spec, priority=None) for spec in specs]
    _ordered(plain)  # unique names
    bus, msgs = _prepare(plain, bitrate, method, id_bits, blocking, fd)
    position = {msg.spec.name: index for index, msg in enumerate(msgs)}
    unplaced = sorted(
        msgs,
        key=lambda msg: (msg.d, msg.t, position[msg.spec.name]),
        reverse=True,
    )
    lower: list[_Msg] = []
    while unplaced:
        misses: list[tuple[str, Fraction | None, Fraction]] = []
        chosen = None
        for candidate in unplaced:
            higher = [msg for msg in unplaced if msg is not candidate]
            r = _response_time(bus, higher, candidate, _blocking(bus, lower))
            if r is not None and r <= candidate.d:
                chosen = candidate
                break
            misses.append((candidate.spec.name, r, candidate.d))
        if chosen is None:
            name, r, d = min(
                misses,
                key=lambda miss: (miss[1] is None, (miss[1] or Fraction(0)) - miss[2]),
            )
            others = sorted(n for n, _, _ in misses if n != name)
            level = len(unplaced)
            detail = (
                f"no priority ordering meets every deadline ({method}, {bitrate} bit/s): "
                f"at priority rank {level - 1} of {len(msgs)} no message fits"
                + (f" (also missing: {', '.join(repr(n) for n in others)})" if others else "")
            )
            raise NotSchedulable(name, r, d, detail)
        unplaced.remove(chosen)
        lower.append(chosen)
    return _ranked([msg.spec for msg in reversed(lower)])


def to_priority_field(
    ordering: Sequence[MessageSpec], *, first: int = 0, last: int = 255
) -> dict[str, int]:
    """Map an ordering onto the 8-bit priority field: name -> value, lower value = higher priority.

    The ordering is the messages' ``priority`` fields if they have them, else the sequence order
    (highest first). The highest-priority message gets ``first``, the next ``first + 1`` and so
    on; raises ``ValueError`` if they do not fit in ``first..last`` (within 0..255).
    """
    if not 0 <= first <= last <= 255:
        raise ValueError(f"need 0 <= first <= last <= 255, not first={first}, last={last}")
    order = _ordered(ordering)
    if len(order) > last - first + 1:
        raise ValueError(f"{len(order)} messages do not fit in priority values {first}..{last}")
    return {spec.name: first + rank for rank, spec in enumerate(order)}


def assign_priorities(
    specs: Sequence[MessageSpec],
    bitrate: int,
    id_bits: int = 29,
    *,
    policy: Policy = "audsley",
    method: Method = "davis2007",
    blocking: Blocking = "max-frame",
    fd: bool = False,
    first: int = 0,
    last: int = 255,
) -> dict[str, int]:
    """Admission test: priority-field values for ``specs`` under which all meet their deadlines.

    ``policy="audsley"`` searches for a schedulable ordering (optimal), ``"deadline-monotonic"``
    orders by deadline, ``"given"`` keeps the order of ``specs`` (their ``priority`` fields or
    sequence order). Returns name -> value in ``first..last`` (see ``to_priority_field``).
    Raises ``NotSchedulable`` naming a message that would miss its deadline (for the fixed
    policies, the highest-priority one that misses), ``ValueError`` for invalid input.
    """
    if policy == "audsley":
        ordering = audsley(specs, bitrate, id_bits, method=method, blocking=blocking, fd=fd)
    elif policy == "deadline-monotonic":
        ordering = deadline_monotonic(specs)
    elif policy == "given":
        ordering = _ranked(_ordered(specs))
    else:
        raise ValueError(f"policy must be one of {', '.join(POLICIES)}, not {policy!r}")
    values = to_priority_field(ordering, first=first, last=last)
    if policy != "audsley":
        results = analyze(ordering, bitrate, method, id_bits, blocking=blocking, fd=fd)
        for result in results:  # highest priority first
            if not result.schedulable:
                raise NotSchedulable(
                    result.name,
                    result.response_time_ms,
                    result.deadline_ms,
                    f"with {policy} priorities ({method}, {bitrate} bit/s)",
                )
    return values
