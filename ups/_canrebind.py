"""Binding a CAN channel again after a Bind contradicted its binding, until the binding holds.

A CAN face that sees one of its bindings contradicted (another UID on the etag, or another etag
for the UID) forgets it and stops delivering and sending on it; ``Rebinding.start`` then asks
the CAN-ECB again, in a task of its own per channel, until an answer stands: refusals may be
stray or forged frames too, and another contradiction may come right after the answer, or while
the node tells the CAN-ECB its role (a CAN-ECB on the same link answers a Holds at once, inside
the send). Refused by the CAN-ECB (no etag, no storage), it asks again, up to ``REBIND_MAX``
seconds apart.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

from . import _canproto as p
from . import _cantransfer as t
from ._canbinding import RETRY_FIRST, Bindings
from ._errors import BrokerUnavailable, Exhausted, PayloadTooLarge
from ._face import ChannelState

log = logging.getLogger("ups.can")

REBIND_MAX = 5.0  #: a refused re-binding is asked again at most this far apart (seconds)


class Rebinding:
    """The channels a CAN face binds again.

    ``running`` maps each UID being bound again to its task (the face's table, which
    ``Bindings`` reads too). ``wants_rx`` is the face's table of subscribed channels being bound
    (UID -> state); ``receive(etag, state)`` makes the face receive a channel bound again (or
    raises ``PayloadTooLarge``: its events are larger than the node buffers); ``send`` and
    ``txnode`` send a management frame and give the node's TxNode. ``counters["task_errors"]``
    counts the re-bindings that failed; ``warn(key, text, *args)`` logs now and then.
    """

    def __init__(
        self,
        running: dict[int, asyncio.Task[None]],
        *,
        bindings: Bindings,
        wants_rx: dict[int, ChannelState],
        receive: Callable[[int, ChannelState], None],
        send: Callable[[p.Management], None],
        txnode: Callable[[], int],
        counters: dict[str, int],
        warn: Callable[..., None],
    ) -> None:
        self.running = running
        self._bindings = bindings
        self._wants_rx = wants_rx
        self._receive = receive
        self._send = send
        self._txnode = txnode
        self._counters = counters
        self._warn = warn

    def start(self, uid: int, state: ChannelState) -> None:
        """Bind ``uid`` again, if the node still uses it and it is not being bound again
        already (a task that runs checks its answer before it ends)."""
        running = self.running.get(uid)
        if not (state.subs or state.published):
            return
        if running is not None and not running.done():
            return
        task = asyncio.get_running_loop().create_task(self._rebind(uid, state))
        self.running[uid] = task
        task.add_done_callback(self._done)

    async def close(self) -> None:
        tasks = list(self.running.values())
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _rebind(self, uid: int, state: ChannelState) -> None:
        bindings = self._bindings
        delay = RETRY_FIRST
        while True:
            if not (state.subs or state.published):
                return  # nobody uses the channel any more
            if state.subs:
                self._wants_rx[uid] = state
            try:
                etag = await bindings.request(p.SUB_BIND if state.subs else p.PUB_BIND, uid)
            except (BrokerUnavailable, Exhausted) as exc:
                self._warn("rebind-wait", "still binding %016x again: %s", uid, exc)
                await asyncio.sleep(delay)
                delay = min(delay * 2, REBIND_MAX)
                continue
            finally:
                self._wants_rx.pop(uid, None)
            if bindings.bound.get(uid) != etag:
                continue  # contradicted before this task ran again
            state.max_size = t.max_size(etag)
            if state.subs:
                try:
                    self._receive(etag, state)
                except PayloadTooLarge as exc:
                    log.warning("not receiving %s any more: %s", state.channel, exc)
                    return
                if state.published:
                    self._send(p.Holds(True, self._txnode(), etag, uid))
            if bindings.bound.get(uid) == etag:  # nothing contradicted it meanwhile
                break
        log.info("channel %s bound again, to etag %#x", state.channel, etag)

    def _done(self, task: asyncio.Task[None]) -> None:
        for uid, running in list(self.running.items()):
            if running is task:
                del self.running[uid]
        if not task.cancelled() and task.exception() is not None:
            self._counters["task_errors"] += 1
            log.error("could not bind a channel again: %s", task.exception())
