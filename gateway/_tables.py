"""Who subscribes to and publishes on each channel of a bus, learnt from what its nodes ask,
for a gateway that does not host the bus's CAN-ECB (``ups gateway --external-can-ecb``)."""

from __future__ import annotations

import collections
from collections.abc import Callable

import can

from ups import _canproto as p
from ups._canlink import CanLink
from ups._errors import DecodeError

#: node requests (etags below 0x10) and SUB_AT / PUB_AT (priorities 0x00 and 0x01)
_REQUEST_FILTERS = [
    {"can_id": 0, "can_mask": p.ETAG_MASK & ~(p.FIRST_ETAG - 1), "extended": True},
    {"can_id": 0, "can_mask": 0xFE << p.PRIORITY_SHIFT, "extended": True},
]


class Tables:
    """Who subscribes to and publishes on each channel of the bus, learnt from the requests
    that nodes send (when the CAN-ECB is not ours). Same interface as ``CanEcb``'s tables."""

    def __init__(self, link: CanLink) -> None:
        self.link = link
        self.subscribers: collections.defaultdict[int, set[int]] = collections.defaultdict(set)
        self.publishers: collections.defaultdict[int, set[int]] = collections.defaultdict(set)
        self.on_change: Callable[[int], None] | None = None
        self._handler = self._on_frame

    def start(self) -> None:
        self.link.add_handler(self._handler, _REQUEST_FILTERS)

    def close(self) -> None:
        self.link.remove_handler(self._handler)

    def _on_frame(self, frame: can.Message) -> None:
        can_id = frame.arbitration_id
        if not frame.is_extended_id or (can_id >> p.TXNODE_SHIFT) & p.TXNODE_MASK == p.MGMT_TXNODE:
            return
        if not p.is_management(can_id):
            return
        try:
            msg = p.decode(can_id, bytes(frame.data))
        except DecodeError:
            return
        if isinstance(msg, p.Holds):
            table, uid, add = self.publishers if msg.publish else self.subscribers, msg.uid, True
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
