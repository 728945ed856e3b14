"""The gateway's backlog: the channels whose forwarding is to be brought in line with the tables,
first changed first, by ``RECONCILERS`` workers at once, each on another channel; one whose
reconcile failed is tried again a second later. Who needs a channel settled waits for it."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Iterable

from ups._errors import UpsError

log = logging.getLogger("ups.gateway")

#: channels whose forwarding is brought in line at once (each waits for the CAN-ECB and the IP
#: side); a flood of forged channels then delays a real one by its share of the backlog only
RECONCILERS = 8


class Backlog:
    """Channels to ``reconcile`` (``counters``: ``reconcile_errors``, its failures)."""

    def __init__(
        self, reconcile: Callable[[int], Awaitable[None]], counters: dict[str, int]
    ) -> None:
        self._reconcile = reconcile
        self._counters = counters
        self.dirty: dict[int, None] = {}  # channels to reconcile, first changed first
        self.running: set[int] = set()  # the channels being reconciled
        self._settled: dict[int, list[asyncio.Future[None]]] = {}  # uid -> awaiting its reconcile
        self._wake = asyncio.Event()

    def changed(self, uid: int) -> None:
        self.dirty[uid] = None
        self._wake.set()

    def changed_all(self, uids: Iterable[int]) -> None:
        self.dirty.update(dict.fromkeys(uids))
        self._wake.set()

    def busy(self, uid: int) -> bool:
        """Whether ``uid`` waits for its reconcile or is being reconciled."""
        return uid in self.dirty or uid in self.running

    async def settled(self, uid: int) -> None:
        """Wait until ``uid`` has been reconciled with no change left (see ``busy`` first)."""
        fut = asyncio.get_running_loop().create_future()
        self._settled.setdefault(uid, []).append(fut)
        await fut

    def _next(self) -> int | None:
        """The channel changed first that nobody reconciles now (None: none)."""
        uid = next((u for u in self.dirty if u not in self.running), None)
        if uid is not None:
            del self.dirty[uid]
            self.running.add(uid)
        return uid

    async def work(self) -> None:
        """Bring changed channels' forwarding in line with the tables, first changed first.
        ``RECONCILERS`` of these run at once, each on another channel: a channel's reconcile
        waits for the CAN-ECB and the IP side, and hundreds of channels changed at once (a
        flood of forged requests) must not hold a real one back for long."""
        while True:
            uid = self._next()
            if uid is None:
                self._wake.clear()
                await self._wake.wait()
                continue
            try:
                await self._reconcile(uid)
            except Exception as exc:  # e.g. the CAN-ECB did not answer: try again later
                self._counters["reconcile_errors"] += 1
                if isinstance(exc, UpsError):
                    log.warning("could not update forwarding of %016x: %s", uid, exc)
                else:
                    log.exception("could not update forwarding of %016x", uid)
                asyncio.get_running_loop().call_later(1.0, self.changed, uid)
            finally:
                self.running.discard(uid)
            if uid in self.dirty:  # changed again meanwhile: another reconciler may take it
                self._wake.set()
            else:
                for fut in self._settled.pop(uid, ()):
                    if not fut.done():
                        fut.set_result(None)
