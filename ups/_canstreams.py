"""Real-time declarations on CAN as a node makes them: the DECLARE fields, the error a Refuse
becomes, and the node's declared streams with the verdicts it takes (``docs/protocol.md``,
"Real-time channels").

A node takes a Grant or a Refuse only for a stream it declared itself (its TxNode, the etag of a
channel it declared); any other is stray or forged: ignored and counted (``stray_verdicts``).
For a declared stream it follows the latest verdict: a Grant sets its priority (also unasked:
another declaration moved it), a Refuse puts it back to best effort. ``declare`` answers with
the verdict that stood ``VERDICT_WAIT`` seconds after the latest one it heard, so that a
forged verdict that comes before the CAN-ECB's answer, or after it, is not taken for the answer:
the CAN-ECB corrects each one it hears, at once.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from . import _canproto as p
from . import _cantransfer as t
from ._canbinding import BIND_TIMEOUT, RETRY_FIRST, RETRY_MAX
from ._errors import BrokerUnavailable, ConfigError, Unschedulable
from ._face import ChannelState

log = logging.getLogger("ups.can")

#: a declaration's answer is the latest verdict, once it has stood this long (longer than the
#: CAN-ECB's analysis of a full bus; its correction of a forged verdict follows at once)
VERDICT_WAIT = 0.5

Fields = tuple[int, int, int, int]  # size, period, deadline, jitter (DECLARE's units)


def declaration(
    size: int, period_ms: float, deadline_ms: float, jitter_ms: float, *, etag: int, mtu: int
) -> Fields:
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


@dataclass
class Declared:
    """One stream this node declared: its fields, the priority it had before (best effort, to
    go back to on a Refuse), the latest verdict, and while ``declare`` waits, its answer."""

    state: ChannelState
    fields: Fields
    fallback: int
    verdict: p.Grant | p.Refuse | None = None
    answer: asyncio.Future[int] | None = None
    timer: asyncio.TimerHandle | None = field(default=None, repr=False)


class Streams:
    """The real-time streams a node declared on one bus. ``send`` puts a frame on the bus,
    ``txnode()`` is the node's TxNode, ``uid_at`` and ``heard`` the node's bindings (etag ->
    UID it relies on, and every Bind it heard), ``counters`` the face's (``stray_verdicts``),
    ``warn`` its rate-limited warning."""

    def __init__(
        self,
        *,
        send: Callable[[p.Management], None],
        txnode: Callable[[], int],
        uid_at: dict[int, int],
        heard: dict[int, int],
        counters: dict[str, int],
        warn: Callable[..., None],
        bus: str,
    ) -> None:
        self._send = send
        self._txnode = txnode
        self._uid_at = uid_at
        self._heard = heard
        self._counters = counters
        self._warn = warn
        self._bus = bus
        self.declared: dict[int, Declared] = {}  # uid -> its declaration

    def close(self) -> None:
        for decl in self.declared.values():
            if decl.timer is not None:
                decl.timer.cancel()
            if decl.answer is not None:
                decl.answer.cancel()

    async def declare(self, state: ChannelState, etag: int, fields: Fields) -> int:
        """Send DECLARE until a verdict comes (request retry), and return the granted priority
        once the latest verdict has stood ``VERDICT_WAIT``; raise ``Unschedulable`` for a
        Refuse, ``BrokerUnavailable`` if none comes within 5 s."""
        uid = state.channel.uid
        old = self.declared.get(uid)
        fallback = old.fallback if old is not None else state.priority
        if old is not None and old.timer is not None:
            old.timer.cancel()
        answer = asyncio.get_running_loop().create_future()
        decl = self.declared[uid] = Declared(state, fields, fallback, answer=answer)
        msg = p.Declare(self._txnode(), etag, *fields)
        delay, waited = RETRY_FIRST, 0.0
        try:
            while True:
                if decl.verdict is None:  # once answered, asking again would only delay it
                    self._send(msg)
                try:
                    return await asyncio.wait_for(asyncio.shield(answer), delay)
                except TimeoutError:
                    if answer.done():  # the answer was an error (BrokerUnavailable is one)
                        return int(answer.result())
                waited += delay
                if waited >= BIND_TIMEOUT:
                    if decl.verdict is None:
                        raise BrokerUnavailable(
                            f"the CAN-ECB on {self._bus} did not admit {state.channel} within "
                            f"{BIND_TIMEOUT:g} s"
                        )
                    self._settle(uid, decl)  # verdicts keep coming: the latest is the answer
                delay = min(delay * 2, RETRY_MAX)
        except BaseException:  # refused, unanswered or cancelled: nothing to re-announce
            if self.declared.get(uid) is decl:
                del self.declared[uid]
                if decl.timer is not None:
                    decl.timer.cancel()
            raise

    def on_verdict(self, msg: p.Grant | p.Refuse) -> None:
        """A Grant or Refuse heard on the bus."""
        if msg.txnode != self._txnode():
            return  # another node's stream
        uid = self._uid_at.get(msg.etag, -1)
        decl = self.declared.get(uid)
        if decl is None:  # no declaration of ours asked for it: stray or forged
            self._counters["stray_verdicts"] += 1
            self._warn("stray-verdict", "ignored a %s for etag %#x: this node declared no "
                       "stream there", type(msg).__name__, msg.etag)  # fmt: skip
            return
        decl.verdict = msg
        if decl.answer is not None and not decl.answer.done():  # the answer is still open
            if decl.timer is not None:
                decl.timer.cancel()
            loop = asyncio.get_running_loop()
            decl.timer = loop.call_later(VERDICT_WAIT, self._settle, uid, decl)
            return
        self._apply(decl, msg)  # admitted: Audsley moved it, or the CAN-ECB corrects

    def _settle(self, uid: int, decl: Declared) -> None:
        decl.timer = None
        verdict, answer = decl.verdict, decl.answer
        if verdict is None or answer is None or answer.done():
            return
        self._apply(decl, verdict)
        if isinstance(verdict, p.Grant):
            answer.set_result(verdict.priority)
        else:
            answer.set_exception(refusal(verdict, uid, self._heard))

    def _apply(self, decl: Declared, verdict: p.Grant | p.Refuse) -> None:
        if isinstance(verdict, p.Grant):
            decl.state.priority = verdict.priority
        elif decl.state.priority != decl.fallback:
            decl.state.priority = decl.fallback
            log.warning("the CAN-ECB refused %s, admitted before: best effort (priority %#x) "
                        "until it grants it again", decl.state.channel, decl.fallback)  # fmt: skip
