"""Real-time declarations on CAN as a node sends them: the DECLARE fields, and the error a
Refuse becomes. Pure functions; the CAN face sends and awaits (``docs/protocol.md``, "Real-time
channels")."""

from __future__ import annotations

from . import _canproto as p
from . import _cantransfer as t
from ._errors import ConfigError, Unschedulable


def declaration(
    size: int, period_ms: float, deadline_ms: float, jitter_ms: float, *, etag: int, mtu: int
) -> tuple[int, int, int, int]:
    """The (size, period, deadline, jitter) fields of a DECLARE on ``etag``: times in units of
    100 us, period and deadline rounded down and jitter up (the safe side); the size in bytes
    on a one-frame etag, in frames of ``mtu`` bytes on a larger one."""
    unit = p.TIME_UNIT_US / 1000
    period, deadline = int(period_ms / unit), int(deadline_ms / unit)
    jitter = -int(-jitter_ms // unit)
    if not 0 <= size <= t.MAX_EVENT:
        raise ConfigError(f"size_bytes must be 0..{t.MAX_EVENT}, got {size}")
    if not (1 <= period <= 0xFFFF and 1 <= deadline <= 0xFFFF and 0 <= jitter <= 0xFF):
        raise ConfigError(
            "period and deadline must be 0.1..6553.5 ms, jitter 0..25.5 ms; got "
            f"{period_ms}, {deadline_ms}, {jitter_ms}"
        )
    if etag >= p.LARGE_FIRST_ETAG:  # a transfer: the analysis counts its frames
        frames = t.frames_for(size, mtu)
        if frames > 0xFF:
            raise ConfigError(
                f"a real-time event takes at most 255 frames; {size} bytes take {frames}"
            )
        size = frames
    return size, period, deadline, jitter


def refusal(msg: p.Refuse, uid: int | None, heard: dict[int, int]) -> Unschedulable:
    """The error a node raises for ``msg``, about its channel ``uid``; ``heard`` maps the
    etags it heard bound to their UIDs (to name the stream that would miss)."""
    if (msg.miss_etag, msg.miss_txnode) == (msg.etag, msg.txnode):
        culprit = "it"
    else:
        other = heard.get(msg.miss_etag)
        name = f"0x{other:016x}" if other is not None else f"etag {msg.miss_etag:#x}"
        culprit = f"channel {name} of TxNode 0x{msg.miss_txnode:02x}"
    if msg.response_10us == p.RESPONSE_UNBOUNDED:
        response = "no bounded response time"
    else:
        response = f"worst-case response {msg.response_10us / 100:g} ms"
    channel = f"0x{uid:016x}" if uid is not None else f"etag {msg.etag:#x}"
    return Unschedulable(
        f"the CAN-ECB refused real-time channel {channel}: with it, {culprit} would miss its "
        f"deadline ({response})"
    )
