"""A CAN node's etag bindings: what it asked the CAN-ECB, and the answers it relies on.

A node relies only on a Bind that answers its own request (see docs/protocol.md, *Binding*).
A Bind that contradicts a binding it relies on (another UID on the etag, or another etag for
the UID) is handed to the face (``on_contradicted``), which stops using the channels involved
and binds them again; an answer to such a re-binding is adopted only after it stood
``SETTLE`` seconds without a contradiction. A refusal (EtagsFull, Failed, Limit) ends a request
only once it has stood ``REFUSAL_WAIT`` seconds while the node kept asking, with no Bind
answering it: anyone can send one. (``_bindings`` is another thing: the tools' view of a bus's
bindings, read from the CAN-ECB or a recording.)
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Container

from . import _canproto as p
from . import _cantransfer as t
from ._errors import BrokerUnavailable

log = logging.getLogger("ups.can")

RETRY_FIRST = 0.05  #: seconds before asking the CAN-ECB again (doubling)
RETRY_MAX = 1.0  #: the longest wait between two asks
BIND_TIMEOUT = 5.0  #: an ask unanswered this long raises BrokerUnavailable
SETTLE = 0.05  #: an answer to a re-binding must stand this long before it is relied on
IN_FLIGHT = 128  #: binding requests outstanding at once (the rest wait their turn)
#: a refusal (TxNodesFull, Failed, EtagsFull, Limit) ends a join or a request once it stood this
#: long with nothing the CAN-ECB said contradicting it (longer than its recovery, 2 s)
REFUSAL_WAIT = 3.0


class Bindings:
    """The node's table: ``bound`` (uid -> etag) and ``uid_at`` (etag -> uid), confirmed by
    the CAN-ECB in answer to this node; ``heard`` (etag -> uid), every Bind heard on the bus.
    The face reads these dicts too. :meth:`ask` also carries the
    face's real-time declarations (the same retries, another answer).

    ``on_adopted(etag, uid)`` is called when an answer is relied on, before its request
    returns; ``on_contradicted(uid)`` when a Bind contradicts ``uid``'s binding (the face
    ``forget``s it and binds it again); ``rebinding`` holds the UIDs the face binds again.
    ``counters`` is the face's: ``moves`` and ``rebinds`` are counted there."""

    def __init__(
        self,
        *,
        send: Callable[[p.Management], None],
        txnode: Callable[[], int],
        bus: str,
        counters: dict[str, int],
        warn: Callable[..., None],
        on_adopted: Callable[[int, int], None],
        on_contradicted: Callable[[int], None],
        rebinding: Container[int],
    ) -> None:
        self._send = send
        self._txnode = txnode
        self._bus = bus
        self._counters = counters
        self._warn = warn
        self._on_adopted = on_adopted
        self._on_contradicted = on_contradicted
        self._rebinding = rebinding
        self.bound: dict[int, int] = {}
        self.uid_at: dict[int, int] = {}
        self.heard: dict[int, int] = {}
        self.pending: dict[int, asyncio.Future[int]] = {}  # uid -> the etag awaited
        #: uid -> since when a refusal of its pending request stands, and the error it ends it
        #: with (the first one's time, the latest one's error); an answer adopted voids it
        self._refused: dict[int, tuple[float, Exception]] = {}
        self._min_class: dict[int, int] = {}  # uid -> the size class its pending request needs
        #: uid being bound again -> the etag an answer gave, adopted if nothing contradicts it
        #: within SETTLE (the CAN-ECB corrects a forged Bind at once)
        self._candidates: dict[int, tuple[int, asyncio.TimerHandle]] = {}
        self._in_flight = asyncio.Semaphore(IN_FLIGHT)

    def close(self) -> None:
        for fut in self.pending.values():
            fut.cancel()
        for _, timer in self._candidates.values():
            timer.cancel()
        self._candidates.clear()

    def forget(self, uid: int) -> int | None:
        """Stop relying on ``uid``'s binding; its etag, if it had one."""
        etag = self.bound.pop(uid, None)
        if etag is not None:
            self.uid_at.pop(etag, None)
        return etag

    async def request(self, kind: int, uid: int, size_class: int = 0) -> int:
        """Ask the CAN-ECB for ``uid``'s etag (SUB_BIND or PUB_BIND, at least ``size_class``)
        until an answer is adopted; one request per UID at a time, shared by its callers."""
        fut = self.pending.get(uid)
        if fut is None:
            fut = self.pending[uid] = asyncio.get_running_loop().create_future()
        if size_class:
            self._min_class[uid] = max(size_class, self._min_class.get(uid, 0))
        try:
            async with self._in_flight:
                if fut.done():  # answered while this request waited its turn
                    return fut.result()
                return await self._ask(p.Request(kind, self._txnode(), uid, size_class), fut)
        finally:
            if self.pending.get(uid) is fut:
                del self.pending[uid]
                self._min_class.pop(uid, None)
                self._refused.pop(uid, None)

    async def _ask(self, msg: p.Request, fut: asyncio.Future[int]) -> int:
        """Send ``msg`` until ``fut`` has the CAN-ECB's answer (50 ms, doubling, 5 s in all),
        or a refusal of it has stood ``REFUSAL_WAIT``."""
        loop = asyncio.get_running_loop()
        delay = RETRY_FIRST
        started = loop.time()
        while True:
            self._send(msg)
            wait = delay
            refused = self._refused.get(msg.value)
            if refused is not None:
                wait = min(wait, max(0.005, refused[0] + REFUSAL_WAIT - loop.time()))
            try:
                return await asyncio.wait_for(asyncio.shield(fut), wait)
            except TimeoutError:
                if fut.done():  # the answer was an error (BrokerUnavailable is a TimeoutError)
                    return fut.result()
            now = loop.time()
            refused = self._refused.get(msg.value)
            if refused is not None and now >= refused[0] + REFUSAL_WAIT:
                raise refused[1]  # it stood: the CAN-ECB's answer
            if now - started >= BIND_TIMEOUT:
                if refused is not None:
                    raise refused[1]
                raise BrokerUnavailable(
                    f"the CAN-ECB on {self._bus} did not bind {msg.value:#018x} within "
                    f"{BIND_TIMEOUT:g} s"
                ) from None
            delay = min(delay * 2, RETRY_MAX)

    def fail(self, uid: int, exc: Exception) -> None:
        """The CAN-ECB (or a forger) says it cannot bind ``uid``: its request raises ``exc``
        once that has stood ``REFUSAL_WAIT`` while the node asked again with no answer."""
        fut = self.pending.get(uid)
        if fut is None or fut.done():
            if uid in self.bound:  # after the answer: stray, forged or late, it changes nothing
                self._counters["stray_refusals"] += 1
            return
        self._counters["refusals"] += 1
        refused = self._refused.get(uid)
        since = asyncio.get_running_loop().time() if refused is None else refused[0]
        self._refused[uid] = (since, exc)

    def on_bind(self, etag: int, uid: int) -> None:
        heard = self.heard.get(etag)
        self.heard[etag] = uid
        self._spoil(etag, uid)  # a candidate this Bind contradicts is not adopted
        old_uid = self.uid_at.get(etag)
        old_etag = self.bound.get(uid)
        if (old_uid is not None and old_uid != uid) or (old_etag is not None and old_etag != etag):
            if old_uid is None and old_etag is not None and _grows(old_etag, etag):
                self._counters["moves"] += 1  # a channel moved to a larger size class: expected
                log.info("%016x moved to etag %#x (size class %d): binding it again", uid, etag,
                         t.size_class(etag))  # fmt: skip
            else:
                self._counters["rebinds"] += 1
                self._warn("rebind", "Bind(%#x, %016x) contradicts this node's bindings: "
                           "binding the channels involved again", etag, uid)  # fmt: skip
            for involved in {old_uid, uid if old_etag is not None else None}:
                if involved is not None:
                    self._on_contradicted(involved)
            return
        fut = self.pending.get(uid)
        if fut is not None and not fut.done():
            if t.size_class(etag) < self._min_class.get(uid, 0):
                return  # an answer to an earlier request, for a smaller class: ours follows
            if heard is not None and heard != uid:  # last heard as another channel's etag:
                self._counters["rebinds"] += 1  # doubt it; adopt it when it comes again
                self._warn("doubt", "Bind(%#x, %016x) names an etag last heard bound to "
                           "%016x: asking again", etag, uid, heard)  # fmt: skip
                return
            if uid in self._rebinding:  # after a contradiction: adopt only an answer that no
                if uid not in self._candidates:  # Bind contradicts for a moment
                    loop = asyncio.get_running_loop()
                    timer = loop.call_later(SETTLE, self._settled, uid, etag)
                    self._candidates[uid] = (etag, timer)
                return
            self._adopt(etag, uid)

    def _adopt(self, etag: int, uid: int) -> None:
        fut = self.pending.get(uid)
        if fut is None or fut.done() or self.uid_at.get(etag, uid) != uid:
            return
        self.bound[uid] = etag
        self.uid_at[etag] = uid
        self._refused.pop(uid, None)  # contradicted: the CAN-ECB bound it after all
        self._on_adopted(etag, uid)
        fut.set_result(etag)

    def _spoil(self, etag: int, uid: int) -> None:
        """Drop the candidates a Bind(etag, uid) contradicts."""
        for other, (candidate, timer) in list(self._candidates.items()):
            if (candidate == etag) != (other == uid):
                timer.cancel()
                del self._candidates[other]

    def _settled(self, uid: int, etag: int) -> None:
        candidate = self._candidates.pop(uid, None)
        if candidate is not None and candidate[0] == etag:
            self._adopt(etag, uid)


def _grows(old_etag: int, etag: int) -> bool:
    """A Bind moving a channel from ``old_etag`` to a larger size class (still a contradiction:
    the node binds again, but it counts a move, not a rebind, and does not warn)."""
    return t.size_class(etag) > t.size_class(old_etag)
