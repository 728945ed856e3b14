"""The CAN-ECB's table of who uses each channel: the TxNodes subscribing to and publishing on
every UID, and per TxNode the channels it uses or is being bound to, for its limit."""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable

from ups import _canproto as p

log = logging.getLogger("ups.can_ecb")


class Channels:
    """``subscribers`` and ``publishers``: uid -> TxNodes (no empty sets). ``changed(uid)`` is
    called whenever either set of a channel changes. A TxNode may use at most ``limit``
    channels, counting those it is being bound to (``asking``): past it, a request is answered
    with Limit and counted (``limited`` in the CAN-ECB's ``counters``)."""

    def __init__(
        self,
        limit: int,
        *,
        send: Callable[[p.Management], None],
        counters: dict[str, int],
        warn: Callable[..., None],
        changed: Callable[[int], None],
    ) -> None:
        self._limit = limit
        self._send = send
        self._counters = counters
        self._warn = warn
        self._changed = changed
        self.subscribers: defaultdict[int, set[int]] = defaultdict(set)
        self.publishers: defaultdict[int, set[int]] = defaultdict(set)
        self.of: defaultdict[int, set[int]] = defaultdict(set)  # TxNode -> the uids it uses
        self.asking: defaultdict[int, set[int]] = defaultdict(set)  # TxNode -> uids being bound

    def within_limit(self, txnode: int, uid: int) -> bool:
        """May ``txnode`` use ``uid``? If not, say so on the bus (Limit)."""
        channels = self.of.get(txnode, ())
        asking = self.asking.get(txnode, ())
        if uid in channels or uid in asking or len(channels) + len(asking) < self._limit:
            return True
        self._counters["limited"] += 1
        self._warn("limit", "TxNode 0x%02x uses %d channels already: refused %016x", txnode,
                   len(channels), uid)  # fmt: skip
        self._send(p.Limit(txnode, uid))
        return False

    def ask(self, txnode: int, uid: int) -> None:
        """``txnode`` waits for ``uid``'s etag to be stored."""
        self.asking[txnode].add(uid)

    def answered(self, txnode: int, uid: int) -> None:
        asking = self.asking.get(txnode)
        if asking is not None:
            asking.discard(uid)
            if not asking:
                del self.asking[txnode]

    def use(self, publish: bool, uid: int, txnode: int) -> None:
        """``txnode`` publishes on (or subscribes to) ``uid``."""
        nodes = (self.publishers if publish else self.subscribers)[uid]
        if txnode not in nodes:
            nodes.add(txnode)
            self.of[txnode].add(uid)
            self._changed(uid)

    def unsubscribe(self, uid: int, txnode: int) -> None:
        nodes = self.subscribers.get(uid)
        if nodes is None or txnode not in nodes:
            return
        nodes.discard(txnode)
        if not nodes:
            del self.subscribers[uid]
        if txnode not in self.publishers.get(uid, ()):
            self.of[txnode].discard(uid)
        self._changed(uid)

    def forget(self, txnode: int) -> None:
        """``txnode`` uses no channel any more (its node joined again, or left for good)."""
        for uid in list(self.of.pop(txnode, ())):
            for table in (self.subscribers, self.publishers):
                nodes = table.get(uid)
                if nodes is not None and txnode in nodes:
                    nodes.discard(txnode)
                    if not nodes:
                        del table[uid]
                    self._changed(uid)
