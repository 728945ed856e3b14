"""Real-time admission on one bus: declared streams, and the priorities that keep them on time.

The CAN-ECB keeps every admitted stream of its bus, keyed by (etag, TxNode). A new declaration
is admitted only if Audsley's priority assignment, with the revised CAN response-time analysis
(Davis et al. 2007), finds an ordering of all streams in which every one meets its deadline.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from fractions import Fraction
from math import ceil

from ups import _canproto as p
from ups.rt import MessageSpec, NotSchedulable, assign_priorities

log = logging.getLogger("ups.can_ecb")

#: Priorities given to declared streams; best-effort channels stay below (0x80 by default),
#: management frames above (0x00, 0x01).
RT_FIRST, RT_LAST = 0x02, 0x7F
Key = tuple[int, int]  # (etag, TxNode)
DECLARE_RATE = 10.0  #: analyses per second and TxNode (a burst of twice that)
REMEMBERED = 4096  #: refusals remembered (answers to repeated declarations, and corrections)


@dataclass(frozen=True)
class Verdict:
    """The frames to send: Grants (the new stream's and every stream moved), or one Refuse."""

    frames: list[p.Grant | p.Refuse]
    admitted: bool


class Admission:
    """The streams of one bus of ``bitrate`` bit/s (CAN FD frames when ``fd``, counted at
    that rate: bit-rate switching only makes them shorter)."""

    def __init__(self, bitrate: int, fd: bool = False) -> None:
        self.bitrate = bitrate
        self.fd = fd
        self.declared: dict[Key, MessageSpec] = {}
        self.granted: dict[Key, int] = {}
        self._asked: dict[Key, p.Declare] = {}
        self._refused: dict[p.Declare, p.Refuse] = {}  # valid while ``declared`` stays as is
        self._last_refusal: dict[Key, p.Refuse] = {}  # the latest Refuse of each stream
        self._tokens: dict[int, tuple[float, float]] = {}  # TxNode -> tokens, when counted

    def within_rate(self, txnode: int) -> bool:
        """May ``txnode``'s declaration be analysed now? (``DECLARE_RATE`` a second, a
        burst of twice that; a repeated declaration costs nothing: see :meth:`repeat`.)"""
        now = time.monotonic()
        tokens, last = self._tokens.get(txnode, (2 * DECLARE_RATE, now))
        tokens = min(2 * DECLARE_RATE, tokens + (now - last) * DECLARE_RATE)
        allowed = tokens >= 1
        self._tokens[txnode] = (tokens - 1 if allowed else tokens, now)
        return allowed

    def repeat(self, msg: p.Declare) -> p.Grant | p.Refuse | None:
        """The verdict already given to exactly this declaration, if it still holds (a node
        that missed the answer asks again; no analysis is needed)."""
        key = (msg.etag, msg.txnode)
        if self._asked.get(key) == msg and key in self.granted:
            return p.Grant(msg.etag, msg.txnode, self.granted[key])
        return self._refused.get(msg)

    def verdict(self, etag: int, txnode: int) -> p.Grant | p.Refuse:
        """What this CAN-ECB says of stream (``etag``, ``txnode``): its Grant if admitted, else
        the Refuse it last sent for it, else a Refuse naming the stream itself as unbounded (it
        was never declared here)."""
        key = (etag, txnode)
        if key in self.granted:
            return p.Grant(etag, txnode, self.granted[key])
        return self._last_refusal.get(key) or p.Refuse(
            etag, txnode, etag, txnode, p.RESPONSE_UNBOUNDED
        )

    def decide(self, msg: p.Declare) -> Verdict:
        key = (msg.etag, msg.txnode)
        unit = Fraction(p.TIME_UNIT_US, 1000)
        size, frames = msg.size_bytes, 1
        if msg.etag >= p.LARGE_FIRST_ETAG:  # a transfer of ``size_bytes`` full frames
            size, frames = (64 if self.fd else 8), msg.size_bytes
        spec = MessageSpec(
            _name(key), size, msg.period * unit, msg.deadline * unit, msg.jitter * unit,
            frames=frames,
        )  # fmt: skip
        candidate = {**self.declared, key: spec}
        try:
            values = assign_priorities(
                [candidate[k] for k in sorted(candidate)], self.bitrate, 29,
                first=RT_FIRST, last=RT_LAST, fd=self.fd,
            )  # fmt: skip
        except NotSchedulable as exc:
            miss = _key(exc.channel)
            response = p.RESPONSE_UNBOUNDED
            if exc.response_time_ms is not None:
                response = min(p.RESPONSE_UNBOUNDED, ceil(exc.response_time_ms * 100))
            log.info("refused %s: %s", spec.name, exc)
            refuse = p.Refuse(msg.etag, msg.txnode, miss[0], miss[1], response)
        except ValueError as exc:  # more streams than priority levels
            log.info("refused %s: %s", spec.name, exc)
            refuse = p.Refuse(msg.etag, msg.txnode, msg.etag, msg.txnode, 0)
        else:
            return self._admit(msg, candidate, values)
        if len(self._refused) < REMEMBERED:
            self._refused[msg] = refuse
        self._last_refusal.pop(key, None)
        self._last_refusal[key] = refuse
        if len(self._last_refusal) > REMEMBERED:
            del self._last_refusal[next(iter(self._last_refusal))]
        return Verdict([refuse], admitted=False)

    def _admit(
        self, msg: p.Declare, candidate: dict[Key, MessageSpec], values: dict[str, int]
    ) -> Verdict:
        key = (msg.etag, msg.txnode)
        self._refused.clear()
        self.declared = candidate
        self._asked[key] = msg
        self._last_refusal.pop(key, None)
        grants: list[p.Grant | p.Refuse] = []
        for k in sorted(candidate):
            priority = values[_name(k)]
            if k == key or self.granted.get(k) != priority:  # Audsley may move others
                self.granted[k] = priority
                grants.append(p.Grant(k[0], k[1], priority))
        return Verdict(grants, admitted=True)

    def forget_etag(self, etag: int) -> None:
        """A channel moved away from ``etag``: the streams declared on it are gone."""
        for key in [k for k in self.declared if k[0] == etag]:
            self._drop(key)
        for key in [k for k in self._last_refusal if k[0] == etag]:
            del self._last_refusal[key]

    def _drop(self, key: Key) -> None:
        self._refused.clear()
        del self.declared[key]
        self.granted.pop(key, None)
        self._asked.pop(key, None)

    def forget(self, txnode: int) -> None:
        """A node joined again: its declarations are gone."""
        for key in [k for k in self.declared if k[1] == txnode]:
            self._drop(key)
        for key in [k for k in self._last_refusal if k[1] == txnode]:
            del self._last_refusal[key]


def _name(key: Key) -> str:
    return f"{key[0]:04x}/{key[1]}"


def _key(name: str) -> Key:
    etag, txnode = name.split("/")
    return int(etag, 16), int(txnode)
