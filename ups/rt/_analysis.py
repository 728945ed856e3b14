"""Worst-case response-time analysis of CAN messages under fixed-priority arbitration.

Two methods:

``davis2007``
    The revised analysis of Davis, Burns, Bril and Lukkien (2007). For message ``m`` with
    frame time ``C_m``, period ``T_m``, queuing jitter ``J_m`` and blocking ``B_m``, the level-m
    busy period is the least fixed point of
    ``t = B_m + sum_{k in hep(m)} ceil((t + J_k) / T_k) C_k``; every instance
    ``q = 0 .. ceil((t_m + J_m) / T_m) - 1`` in it waits
    ``w(q) = B_m + q C_m + sum_{k in hp(m)} ceil((w(q) + J_k + tau_bit) / T_k) C_k`` and responds
    in ``R(q) = J_m + w(q) - q T_m + C_m``; ``R_m`` is the largest ``R(q)``. Frame times are the
    worst case with bit stuffing (``frame_bits(..., stuffing="worst")``).

``tindell1994``
    The computation behind Table 1 of paper 000, the first-instance analysis of Tindell and Burns
    (1994; Tindell, Burns and Wellings 1995): ``R_m = J_m + w_m + C_m`` with
    ``w_m = B_m + sum_{k in hp(m)} ceil((w_m + J_k + tau_bit) / T_k) C_k``. As paper 000 applies
    it, the message's own queuing jitter ``J_m`` is left out of ``R_m`` (section 4.2: "J_m is not
    factored into the calculations in Table 1. However, the rest of the calculation remains
    intact"), so ``R_m = w_m + C_m``; the higher-priority messages' jitter ``J_k`` still counts in
    ``w_m``. Frame times come from ``8s + g + 13 + floor((g + 8s) / 5)`` (63 bits for one byte,
    130 for eight, 11-bit identifiers). It is optimistic: it leaves out ``J_m``, under-counts stuff
    bits, and misses the push-through of a message's own earlier instance.

Blocking ``B_m`` is, by default (``blocking="max-frame"``), the longest frame of the bus's format
(8 data bytes, or 64 with CAN FD), because a UPS bus may carry foreign frames outside the
analysed set and, once started, any frame delays every message; this is also the blocking of
paper 000's Table 1 ("this message is, in the worst case, the maximum message size"). With
``blocking="lower-priority"`` it is the longest frame of a lower-priority message of the set
(zero for the lowest), the textbook term, valid only when the set is all the bus's traffic. With
the same blocking choice, ``davis2007`` is never below ``tindell1994``.

A message of ``frames`` > 1 (an event sent as several frames) interferes with lower-priority
messages by all its frames, ``C_m = frames x C_frame``; it blocks higher-priority ones by one
frame; its own instance ``q`` waits for its earlier frames too,
``w(q) = B_m + q C_m + (frames - 1) C_frame + ...``, and responds when its last frame ends,
``R(q) = J_m + w(q) - q T_m + C_frame``.

All arithmetic is exact (``fractions.Fraction``, times in milliseconds).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Literal

from ._frames import _tindell_frame_bits, frame_bits
from ._model import MessageSpec, Result, _ordered

Method = Literal["davis2007", "tindell1994"]
Blocking = Literal["max-frame", "lower-priority"]

METHODS: tuple[Method, ...] = ("davis2007", "tindell1994")
BLOCKINGS: tuple[Blocking, ...] = ("max-frame", "lower-priority")


@dataclass(frozen=True)
class _Msg:
    """One message as the analysis sees it: times in ms, exact."""

    spec: MessageSpec
    c: Fraction  # every frame of an instance
    cf: Fraction  # one frame
    t: Fraction
    j: Fraction
    d: Fraction


@dataclass(frozen=True)
class _Bus:
    """Bus parameters shared by every message of one analysis."""

    method: Method
    tau: Fraction
    max_frame: Fraction
    blocking: Blocking


def _check(bitrate: int, method: str, id_bits: int, blocking: str) -> None:
    if isinstance(bitrate, bool) or not isinstance(bitrate, int) or bitrate <= 0:
        raise ValueError(f"bitrate must be a positive integer (bit/s), not {bitrate!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, not {method!r}")
    if id_bits not in (11, 29):
        raise ValueError(f"id_bits must be 11 or 29, not {id_bits!r}")
    if blocking not in BLOCKINGS:
        raise ValueError(f"blocking must be one of {', '.join(BLOCKINGS)}, not {blocking!r}")


def _prepare(
    specs: Sequence[MessageSpec],
    bitrate: int,
    method: Method,
    id_bits: int,
    blocking: Blocking,
    fd: bool,
) -> tuple[_Bus, list[_Msg]]:
    """Check the parameters and turn ``specs`` (in the given order) into analysis messages."""
    _check(bitrate, method, id_bits, blocking)
    tau = Fraction(1000, bitrate)
    if method == "tindell1994":
        if fd:
            raise ValueError("tindell1994 covers classic CAN only, not CAN FD")
        bits = [_tindell_frame_bits(spec.size_bytes, id_bits) for spec in specs]
        longest = _tindell_frame_bits(8, id_bits)
    else:
        bits = [frame_bits(spec.size_bytes, id_bits, "worst", fd) for spec in specs]
        longest = frame_bits(64 if fd else 8, id_bits, "worst", fd)
    messages = [
        _Msg(
            spec=spec,
            c=n * tau * spec.frames,
            cf=n * tau,
            t=spec.period_ms,
            j=spec.jitter_ms,
            d=spec.deadline_ms,
        )
        for spec, n in zip(specs, bits, strict=True)
    ]
    return _Bus(method, tau, longest * tau, blocking), messages


def _blocking(bus: _Bus, lower: Sequence[_Msg]) -> Fraction:
    if bus.blocking == "max-frame":
        return bus.max_frame
    return max((msg.cf for msg in lower), default=Fraction(0))


def _utilisation(msgs: Sequence[_Msg]) -> Fraction:
    return sum((msg.c / msg.t for msg in msgs), Fraction(0))


def _queuing(base: int, higher: Sequence[tuple[int, int, int]], start: int, tau: int) -> int:
    """Least fixed point >= ``start`` of ``w = base + sum ceil((w + J_k + tau) / T_k) C_k``,
    in integer time units; ``higher`` holds (C_k, T_k, J_k).

    The caller guarantees that the utilisation of ``higher`` is below 1, so it exists.
    """
    w = start
    while True:
        following = base + sum(-((-(w + j + tau)) // t) * c for c, t, j in higher)
        if following == w:
            return w
        w = following


def _response_time(bus: _Bus, higher: Sequence[_Msg], m: _Msg, b: Fraction) -> Fraction | None:
    """Worst-case response time of ``m`` below the messages ``higher`` with blocking ``b``.

    The recurrences run on integers: every time is scaled by the least common multiple of the
    denominators involved (exact, and much faster than Fractions on long busy periods).
    """
    level = [*higher, m]
    if _utilisation(higher if bus.method == "tindell1994" else level) >= 1:
        return None
    times = [b, bus.tau, *(x for k in level for x in (k.c, k.t, k.j))]
    unit = math.lcm(*(x.denominator for x in times))

    def scaled(x: Fraction) -> int:
        return int(x * unit)

    hp = [(scaled(k.c), scaled(k.t), scaled(k.j)) for k in higher]
    hp_sum = sum(c for c, _, _ in hp)
    base, tau = scaled(b), scaled(bus.tau)
    mc, mt, mj, mcf = scaled(m.c), scaled(m.t), scaled(m.j), scaled(m.cf)
    before_last = mc - mcf  # the instance's other frames go first, at the same priority
    if bus.method == "tindell1994":
        w = _queuing(base + before_last, hp, base + before_last + hp_sum, tau)
        return Fraction(w + mcf, unit)  # paper 000 leaves out J_m, not the J_k inside w_m
    everyone = [*hp, (mc, mt, mj)]
    t = base + hp_sum + mc
    while True:
        following = base + sum(-((-(t + j)) // period) * c for c, period, j in everyone)
        if following == t:
            break
        t = following
    instances = -((-(t + mj)) // mt)
    worst = 0
    w = 0
    for q in range(instances):
        start = base + q * mc + before_last
        w = _queuing(start, hp, max(w, start + hp_sum), tau)
        worst = max(worst, mj + w - q * mt + mcf)
    return Fraction(worst, unit)


def analyze(
    specs: Sequence[MessageSpec],
    bitrate: int,
    method: Method = "davis2007",
    id_bits: int = 29,
    *,
    blocking: Blocking = "max-frame",
    fd: bool = False,
) -> list[Result]:
    """Analyse a message set on a CAN bus of ``bitrate`` bit/s; results follow the input order.

    Priorities come from the ``priority`` fields, or from the order of ``specs`` when no message
    has one (see ``MessageSpec``). ``method``, ``blocking`` and ``fd`` are described in the module
    documentation of ``ups.rt._analysis``. Raises ``ValueError`` for invalid parameters, duplicate
    names or priorities, or payloads the frame format cannot carry.
    """
    order = _ordered(specs)
    bus, msgs = _prepare(order, bitrate, method, id_bits, blocking, fd)
    by_name: dict[str, Result] = {}
    for index, m in enumerate(msgs):
        r = _response_time(bus, msgs[:index], m, _blocking(bus, msgs[index + 1 :]))
        by_name[m.spec.name] = Result(
            name=m.spec.name,
            response_time_ms=r,
            deadline_ms=m.d,
            schedulable=r is not None and r <= m.d,
        )
    return [by_name[spec.name] for spec in specs]
