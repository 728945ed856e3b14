"""A CAN node's answer to a CAN-ECB's Hello, and to being moved to another TxNode
(docs/protocol.md, *Restarts, recovery and the answer to Hello*): CLAIM of its TxNode, then
SUB_AT / PUB_AT of every binding it relies on at the moment each frame is sent, then DECLARE of
each stream it declared; at most once per ``HELLO_GAP`` (a later Hello is answered when the gap
has passed)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Mapping

from . import _canproto as p
from ._canstreams import Declared
from ._face import ChannelState

log = logging.getLogger("ups.can")

ANNOUNCE_GAP = 0.001  #: pacing of the burst of announcements after a CAN-ECB's Hello
HELLO_GAP = 1.0  #: at most one announcement per this many seconds, however many Hellos


class Announcer:
    """Announces node ``node_id`` (its TxNode: ``txnode()``): its ``channels``, the bindings it
    relies on (``bound``: uid -> etag) and its ``declared`` streams. A failed announcement is
    counted in ``counters["task_errors"]``."""

    def __init__(
        self,
        *,
        send: Callable[[p.Management], None],
        node_id: int,
        txnode: Callable[[], int | None],
        channels: Mapping[int, ChannelState],
        bound: Mapping[int, int],
        declared: Mapping[int, Declared],
        counters: dict[str, int],
    ) -> None:
        self._send = send
        self._node_id = node_id
        self._txnode = txnode
        self._channels = channels
        self._bound = bound
        self._declared = declared
        self._counters = counters
        self.task: asyncio.Task[None] | None = None
        self._last = -HELLO_GAP

    def announce(self, at_once: bool = False) -> None:
        """Announce (``at_once``: without waiting for the gap, as after a move)."""
        if at_once:
            self._last = -HELLO_GAP
        if self.task is None or self.task.done():
            self.task = asyncio.get_running_loop().create_task(self._announce())
            self.task.add_done_callback(self._done)

    async def _announce(self) -> None:
        wait = self._last + HELLO_GAP - time.monotonic()
        if wait > 0:
            await asyncio.sleep(wait)
        self._last = time.monotonic()
        txnode = self._txnode()
        if txnode is None:
            return
        self._send(p.Request(p.CLAIM, txnode, self._node_id))
        for state in list(self._channels.values()):
            uid = state.channel.uid
            roles = [False] if state.subs else []
            if state.published:
                roles.append(True)
            for publish in roles:
                await asyncio.sleep(ANNOUNCE_GAP)
                etag = self._bound.get(uid)  # now: a contradiction may have come meanwhile
                if etag is not None and txnode == self._txnode():
                    self._send(p.Holds(publish, txnode, etag, uid))
            declared = self._declared.get(uid)
            if declared is not None and state.published:
                await asyncio.sleep(ANNOUNCE_GAP)
                etag = self._bound.get(uid)
                if etag is not None and txnode == self._txnode():
                    self._send(p.Declare(txnode, etag, *declared.fields))

    def _done(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            self._counters["task_errors"] += 1
            log.error("announcing this node failed: %s", task.exception())
