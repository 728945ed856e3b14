"""The CAN-ECB's answers to Roster requests: who uses which channel of the bus, for a node that
joins a running bus and must learn what was bound before it came (a gateway with
``--external-can-ecb``, or one whose CAN-ECB stands by for another).

A Roster(cursor) from a joined TxNode is answered with Uses(publish, t, uid) for every TxNode
that subscribes to or publishes on each channel whose UID is ``cursor`` or higher, in UID order,
whole channels, until at least ``PAGE`` frames were listed, then RosterEnd(the asker, the next
UID to ask from, or done). Bounds (docs/protocol.md): at most ``RATE`` roster frames a second,
all answers together, ``BURST`` back to back after a quiet spell, so no asker (a forger
included) takes more of the bus than that; one request waits per TxNode (a newer one replaces
it: ``roster_replaced``); nothing is answered during a recovery window (the tables are being
relearnt), and everything waiting is dropped when the CAN-ECB stands by.
"""

from __future__ import annotations

import asyncio
import collections
import time
from collections.abc import Callable, Mapping

from ups import _canproto as p

PAGE = 32  #: Uses frames in one answer, at least (whole channels: at most PAGE + 253)
RATE = 200.0  #: roster frames a second, at most, all answers together
BURST = 48  #: roster frames sent back to back after a quiet spell


class Rosters:
    """Answers Roster requests from ``subscribers`` and ``publishers`` (uid -> TxNodes, the
    CAN-ECB's live tables), sending by ``send``; ``recovering()`` holds the answers back."""

    def __init__(
        self,
        subscribers: Mapping[int, set[int]],
        publishers: Mapping[int, set[int]],
        *,
        send: Callable[[p.Management], None],
        counters: dict[str, int],
        recovering: Callable[[], bool],
    ) -> None:
        self._subscribers = subscribers
        self._publishers = publishers
        self._send = send
        self._counters = counters
        self._recovering = recovering
        self._waiting: dict[int, int] = {}  # TxNode -> the cursor it asked from, oldest first
        self._out: collections.deque[p.Management] = collections.deque()
        self._tokens = float(BURST)
        self._refilled = time.monotonic()
        self._timer: asyncio.TimerHandle | None = None
        counters.update(rosters=0, roster_frames=0, roster_replaced=0)

    def ask(self, msg: p.Roster) -> None:
        """A joined node's Roster."""
        self._counters["rosters"] += 1
        if self._waiting.pop(msg.txnode, None) is not None:
            self._counters["roster_replaced"] += 1
        self._waiting[msg.txnode] = msg.cursor
        self.pump()

    def close(self) -> None:
        """Drop what waits (the CAN-ECB stops, or stands by)."""
        self._waiting.clear()
        self._out.clear()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def pump(self) -> None:
        """Send what the rate allows now; come back when more is allowed."""
        if self._timer is not None or self._recovering():
            return
        now = time.monotonic()
        self._tokens = min(float(BURST), self._tokens + (now - self._refilled) * RATE)
        self._refilled = now
        while self._tokens >= 1.0:
            if not self._out:
                if not self._waiting:
                    return
                txnode = next(iter(self._waiting))
                self._out.extend(self._page(txnode, self._waiting.pop(txnode)))
            self._send(self._out.popleft())
            self._tokens -= 1.0
            self._counters["roster_frames"] += 1
        if self._out or self._waiting:
            wait = (1.0 - self._tokens) / RATE
            self._timer = asyncio.get_running_loop().call_later(wait, self._due)

    def _due(self) -> None:
        self._timer = None
        self.pump()

    def _page(self, asker: int, cursor: int) -> list[p.Management]:
        """One answer: whole channels from ``cursor`` on, ``PAGE`` frames or more, then the
        RosterEnd."""
        uids = sorted(
            {u for u in self._subscribers if u >= cursor}
            | {u for u in self._publishers if u >= cursor}
        )
        frames: list[p.Management] = []
        for uid in uids:
            if len(frames) >= PAGE:
                return [*frames, p.RosterEnd(asker, uid, False)]
            for publish, table in ((False, self._subscribers), (True, self._publishers)):
                frames.extend(p.Uses(publish, t, uid) for t in sorted(table.get(uid, ())))
        return [*frames, p.RosterEnd(asker, 0, True)]
