"""Who subscribes to and publishes on each channel of a bus, learnt from what its nodes ask,
for a gateway that does not host the bus's CAN-ECB (``ups gateway --external-can-ecb``).

What was bound before the gateway came, it learns from the CAN-ECB itself: once its node has
joined it asks for the roster (Roster, answered with Uses frames and a RosterEnd, page by page;
docs/protocol.md), and asks again for a page that did not come within ``ROSTER_RETRY`` s, at
most ``ROSTER_TRIES`` times in a row (a CAN-ECB older than the Roster frame never answers:
then only what nodes register later, or announce to a restarted CAN-ECB, is forwarded)."""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Callable

import can

from ups import _canproto as p
from ups._canlink import CanLink
from ups._errors import DecodeError

log = logging.getLogger("ups.gateway")

#: node requests (etags below 0x10) and SUB_AT / PUB_AT (priorities 0x00 and 0x01), which take
#: in the CAN-ECB's Uses and RosterEnd frames too (priority 0x00)
_REQUEST_FILTERS = [
    {"can_id": 0, "can_mask": p.ETAG_MASK & ~(p.FIRST_ETAG - 1), "extended": True},
    {"can_id": 0, "can_mask": 0xFE << p.PRIORITY_SHIFT, "extended": True},
]
ROSTER_RETRY = 2.0  #: seconds a page of the roster may take before it is asked for again
ROSTER_TRIES = 10  #: asks in a row without an answer, then the gateway stops asking


class Tables:
    """Who subscribes to and publishes on each channel of the bus, learnt from the requests
    that nodes send (when the CAN-ECB is not ours). Same interface as ``CanEcb``'s tables."""

    def __init__(self, link: CanLink) -> None:
        self.link = link
        self.subscribers: collections.defaultdict[int, set[int]] = collections.defaultdict(set)
        self.publishers: collections.defaultdict[int, set[int]] = collections.defaultdict(set)
        self.on_change: Callable[[int], None] | None = None
        self._handler = self._on_frame
        self._asker: int | None = None  # our TxNode while we ask for the roster
        self._cursor = 0  # the UID the page we wait for starts at
        self._tries = 0
        self._timer: asyncio.TimerHandle | None = None
        self.counters = {"roster_pages": 0, "roster_uses": 0, "roster_retries": 0}

    def start(self) -> None:
        self.link.add_handler(self._handler, _REQUEST_FILTERS)

    def close(self) -> None:
        self.link.remove_handler(self._handler)
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def ask_roster(self, txnode: int) -> None:
        """Ask the CAN-ECB who uses what, from the lowest UID on, as the node holding
        ``txnode`` (the gateway's own)."""
        self._asker, self._cursor, self._tries = txnode, 0, 0
        self._ask()

    def _ask(self) -> None:
        if self._asker is None:
            return
        if self._tries >= ROSTER_TRIES:
            log.warning("the CAN-ECB did not answer the roster (%d tries): channels bound "
                        "before the gateway came are forwarded once their nodes ask again",
                        self._tries)  # fmt: skip
            self._asker = None
            return
        if self._tries:
            self.counters["roster_retries"] += 1
        self._tries += 1
        can_id, data = p.encode(p.Roster(self._asker, self._cursor))
        self.link.send(can_id, data, self._handler)
        if self._timer is not None:
            self._timer.cancel()
        self._timer = asyncio.get_running_loop().call_later(ROSTER_RETRY, self._ask)

    def _on_frame(self, frame: can.Message) -> None:
        can_id = frame.arbitration_id
        if not frame.is_extended_id or not p.is_management(can_id):
            return
        try:
            msg = p.decode(can_id, bytes(frame.data))
        except DecodeError:
            return
        if isinstance(msg, p.RosterEnd):
            self._roster_end(msg)
            return
        if isinstance(msg, p.Holds | p.Uses):
            table, uid, add = self.publishers if msg.publish else self.subscribers, msg.uid, True
            self.counters["roster_uses"] += isinstance(msg, p.Uses)
        elif isinstance(msg, p.Request) and msg.kind != p.CLAIM:
            table = self.subscribers if msg.kind in (p.SUB_BIND, p.UNSUB) else self.publishers
            uid, add = msg.value, msg.kind != p.UNSUB
        else:
            return
        nodes = table[uid]
        before = len(nodes)
        if add:
            nodes.add(msg.txnode)
        else:
            nodes.discard(msg.txnode)
        if not nodes:
            del table[uid]
        if before != len(nodes) and self.on_change is not None:
            self.on_change(uid)

    def _roster_end(self, msg: p.RosterEnd) -> None:
        """The end of a page: ask for the next one, or the roster is whole."""
        if msg.txnode != self._asker:
            return  # another node's answer (its Uses were taken all the same)
        self.counters["roster_pages"] += 1
        if msg.done:
            log.info("learnt the bus's roster: %d channels subscribed to, %d published on",
                     len(self.subscribers), len(self.publishers))  # fmt: skip
            self._asker = None
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            return
        self._cursor, self._tries = msg.next, 0
        self._ask()
