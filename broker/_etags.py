"""The CAN-ECB's etag table: which channel (64-bit UID) is sent under which 14-bit etag.

A node asks for a channel's etag (SUB_BIND, PUB_BIND, with the size class its events need);
the answer, Bind, is sent once the binding is stored. A channel that needs a larger size class
moves to a new etag (its nodes see the contradiction and bind it again). In a recovery window
requests for new bindings wait (at most ``MAX_DEFERRED``), and the bindings nodes report
holding (Holds) are adopted when they contradict nothing; a report that contradicts the tables
is answered with the tables' own Binds. When no etag of a class is free, the one unused
longest is reclaimed once past the lease. A node id may create ``_quota.QUOTA`` bindings: past
it, the one it created that was unused longest is reclaimed once past the lease, else its
request is answered with Limit. See docs/protocol.md, *Binding* and *Bounds*.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable, Mapping

from ups import _canproto as p
from ups import _cantransfer as sizes

from ._admission import Admission
from ._channels import Channels
from ._quota import Quota
from ._store import Store, Write
from ._txnodes import Phase

log = logging.getLogger("ups.can_ecb")

GATE_TIMEOUT = 1.0  #: the longest a publisher's binding waits for the gateway
MAX_DEFERRED = 4096  #: binding requests held during the recovery window
_ANSWER_ONLY = -1  #: in a pending binding's asks: a SUB_BIND its node took back (UNSUB) meanwhile


class Etags:
    """``uid_at`` (etag -> UID) beside the store's UID -> etag; ``seen`` (etag -> when its
    last event came, else the start) for the lease; ``deferred``: the requests held during a
    recovery window, answered by :meth:`replay`. ``gate(uid, txnode)``, when set, is awaited (at
    most ``GATE_TIMEOUT`` s) before the Bind answering publisher ``txnode`` is sent.

    Handed the CAN-ECB's ``phase``, its channel table (``channels``: who uses each channel,
    each TxNode's limit), its ``admission`` (streams declared on an etag that is left are
    dropped), ``assigned`` (TxNode -> the node id that holds it), the ``quota`` of bindings
    each node id may create, its ``send``, ``counters`` (bound, deferred, refused, moved,
    adopted, conflicts, reclaimed, quota_hit), rate-limited ``warn``, and
    ``stored``/``log_failure`` to report writes."""

    def __init__(
        self,
        store: Store,
        *,
        phase: Phase,
        channels: Channels,
        admission: Admission,
        assigned: Mapping[int, int],
        quota: Quota,
        send: Callable[[p.Management], None],
        counters: dict[str, int],
        warn: Callable[..., None],
        stored: Callable[[BaseException | None, str, int | None], bool],
        log_failure: Callable[[str], Callable[[BaseException | None], None]],
        lease: float,
    ) -> None:
        self._store = store
        self._phase = phase
        self._channels = channels
        self._admission = admission
        self._assigned = assigned
        self._quota = quota
        self._send = send
        self._counters = counters
        self._warn = warn
        self._stored = stored
        self._log_failure = log_failure
        self._lease = lease
        self.gate: Callable[[int, int], Awaitable[None]] | None = None
        self.uid_at = {e: u for u, e in store.etags.items()}  # etag -> UID
        #: uid -> the etag being stored for it, and the (kind, TxNode, size class) waiting for it
        self._pending: dict[int, tuple[int, list[tuple[int, int, int]]]] = {}
        self._storing: set[int] = set()  # the etags of _pending
        #: size class -> no etag of that class below it is free
        self._free_from = [sizes.class_etags(c).start for c in range(p.SIZE_CLASSES)]
        self.seen: dict[int, float] = {}  # etag -> last event (default: start time)
        self._started = time.monotonic()
        self.deferred: dict[tuple[int, int, int, int], None] = {}
        self._gated: set[asyncio.Task[None]] = set()

    def close(self) -> None:
        for task in self._gated:
            task.cancel()

    def replay(self) -> None:
        """The recovery window is over: answer the requests it held."""
        deferred, self.deferred = list(self.deferred), {}
        for kind, txnode, uid, size_class in deferred:
            self.on_request(p.Request(kind, txnode, uid, size_class))

    def truth(self, etag: int, uid: int) -> list[p.Bind]:
        """The tables' Binds of ``etag`` and of ``uid`` where they differ from (etag, uid)."""
        binds = []
        if etag in self.uid_at:
            binds.append(p.Bind(etag, self.uid_at[etag]))
        if uid in self._store.etags and self._store.etags[uid] != etag:
            binds.append(p.Bind(self._store.etags[uid], uid))
        return binds

    def correct(self, etag: int, uid: int) -> None:
        """Repeat the tables' truth about ``etag`` and ``uid``."""
        for bind in self.truth(etag, uid):
            self._send(bind)

    def on_request(self, msg: p.Request) -> None:
        """Bind ``uid`` to an etag of at least the asked size class: the one it has, or a new
        one (a channel that needs a larger class moves; its nodes see the contradiction and
        bind it again)."""
        uid, txnode, size_class = msg.value, msg.txnode, msg.size_class
        etag = self._store.etags.get(uid)
        fits = etag is not None and sizes.size_class(etag) >= size_class
        if self._phase.recovering and not fits:
            if len(self.deferred) < MAX_DEFERRED:
                self._counters["deferred"] += 1
                self.deferred[(msg.kind, txnode, uid, size_class)] = None
            return
        if not self._channels.within_limit(txnode, uid):
            return
        if etag is not None and fits:
            self._bound(msg.kind, txnode, uid, etag)
            return
        pending = self._pending.get(uid)
        if pending is not None:
            pending[1].append((msg.kind, txnode, size_class))
            self._channels.ask(txnode, uid)
            return
        creator = self._assigned.get(txnode)
        writes: list[Write] = []
        if creator is None or not self._within_quota(writes, creator, txnode, uid, size_class):
            return
        etag = self._free(writes, size_class)
        if etag is None:
            self._counters["refused"] += 1
            self._warn("etags", "no etag of size class %d left for channel %016x", size_class,
                       uid)  # fmt: skip
            self._send(p.EtagsFull(uid))
            return
        if uid in self._store.etags:
            self._counters["moved"] += 1
            log.info("channel %016x moves to etag %#x (size class %d)", uid, etag, size_class)
        self._pending[uid] = (etag, [(msg.kind, txnode, size_class)])
        self._storing.add(etag)
        self._channels.ask(txnode, uid)
        self._quota.reserve(uid, creator, size_class)
        writes += [("etags", uid, etag), ("creators", uid, creator)]
        self._store.submit(writes, self._stored_for(uid, etag))

    def unsubscribed(self, uid: int, txnode: int) -> None:
        """UNSUB of ``uid`` from ``txnode``: a SUB_BIND of it still held (recovery) is dropped,
        and one waiting for ``uid``'s etag to be stored is answered (the node may publish on
        it too) without making the node a subscriber."""
        for key in [k for k in self.deferred if k[:3] == (p.SUB_BIND, txnode, uid)]:
            del self.deferred[key]
        pending = self._pending.get(uid)
        if pending is not None:
            asks = pending[1]
            asks[:] = [
                (_ANSWER_ONLY if kind == p.SUB_BIND and t == txnode else kind, t, cls)
                for kind, t, cls in asks
            ]

    def _within_quota(
        self, writes: list[Write], creator: int, txnode: int, uid: int, size_class: int
    ) -> bool:
        """May node ``creator`` (at ``txnode``) create a binding of ``size_class``? Past its
        quota, the one it created that was unused longest is reclaimed, once past the lease;
        else it is told so (Limit) and it is counted."""
        if self._quota.allows(creator, size_class) or self._reclaim_own(
            writes, creator, size_class
        ):
            return True
        self._counters["quota_hit"] += 1
        self._warn("quota", "node %016x (TxNode 0x%02x) created %d bindings of size class %d, "
                   "its quota: refused %016x", creator, txnode,
                   self._quota.used(creator, size_class), size_class, uid)  # fmt: skip
        self._send(p.Limit(txnode, uid))
        return False

    def _reclaim_own(self, writes: list[Write], creator: int, size_class: int) -> bool:
        now = time.monotonic()
        if now - self._started < self._lease:  # nothing can have been unused that long
            return False
        idle = [self._store.etags[u] for u in self._quota.created_by(creator, size_class)]
        oldest = min(filter(self._idle, idle), key=self._last_use, default=None)
        if oldest is None or now - self._last_use(oldest) < self._lease:
            return False
        self._reclaim(writes, oldest)
        self._free_from[size_class] = min(self._free_from[size_class], oldest)
        return True

    def _idle(self, etag: int) -> bool:
        """No node the CAN-ECB knows uses ``etag``'s channel, and it is not being stored."""
        uid = self.uid_at.get(etag)
        return (
            uid is not None
            and etag not in self._storing
            and not self._channels.subscribers.get(uid)
            and not self._channels.publishers.get(uid)
        )

    def _last_use(self, etag: int) -> float:
        return self.seen.get(etag, self._started)

    def _reclaim(self, writes: list[Write], etag: int) -> None:
        """Unbind ``etag``, unused past the lease: its etag is free, its creator's quota too."""
        old_uid = self.uid_at.pop(etag)
        del self._store.etags[old_uid]
        self._quota.release(old_uid)
        writes += [("etags", old_uid, None), ("creators", old_uid, None)]
        self._counters["reclaimed"] += 1
        log.warning("reclaimed etag %#x of channel %016x, unused", etag, old_uid)

    def _stored_for(self, uid: int, etag: int) -> Callable[[BaseException | None], None]:
        def done(error: BaseException | None) -> None:
            _, asks = self._pending.pop(uid)
            self._storing.discard(etag)
            for _, txnode, _ in asks:
                self._channels.answered(txnode, uid)
            if not self._stored(error, f"etag {etag:#x} of channel {uid:016x}", uid):
                self._quota.cancel(uid)
                cls = sizes.size_class(etag)
                self._free_from[cls] = min(self._free_from[cls], etag)
                return
            self._counters["bound"] += 1
            self._hold(uid, etag)
            self._quota.commit(uid)
            for kind, txnode, size_class in asks:
                if txnode not in self._assigned:
                    continue
                if kind == _ANSWER_ONLY:  # it left meanwhile (UNSUB): answered, not a subscriber
                    self._send(p.Bind(etag, uid))
                elif sizes.size_class(etag) >= size_class:
                    self._bound(kind, txnode, uid, etag)
                else:  # asked for more while a smaller etag was being stored
                    self.on_request(p.Request(kind, txnode, uid, size_class))

        return done

    def _bound(self, kind: int, txnode: int, uid: int, etag: int) -> None:
        publish = kind == p.PUB_BIND
        self._channels.use(publish, uid, txnode)
        if publish and self.gate is not None:
            task = asyncio.get_running_loop().create_task(self._gated_bind(etag, uid, txnode))
            self._gated.add(task)
            task.add_done_callback(self._gated.discard)
        else:
            self._send(p.Bind(etag, uid))

    async def _gated_bind(self, etag: int, uid: int, txnode: int) -> None:
        assert self.gate is not None
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(GATE_TIMEOUT):
                await self.gate(uid, txnode)
        self._send(p.Bind(etag, uid))

    def _free(self, writes: list[Write], size_class: int) -> int | None:
        pending = self._storing
        etags = sizes.class_etags(size_class)
        etag = self._free_from[size_class]  # no etag of the class below it is free
        while etag < etags.stop and (etag in self.uid_at or etag in pending):
            etag += 1
        self._free_from[size_class] = etag
        if etag < etags.stop:
            return etag
        now = time.monotonic()
        idle = [e for e in self.uid_at if e in etags and self._idle(e)]
        oldest = min(idle, key=self._last_use, default=None)
        if oldest is None or now - self._last_use(oldest) < self._lease:
            return None
        self._reclaim(writes, oldest)
        return oldest

    def _hold(self, uid: int, etag: int) -> None:
        old = self._store.etags.get(uid)
        if old is not None and old != etag:  # the channel moved to a larger size class
            del self.uid_at[old]
            cls = sizes.size_class(old)
            self._free_from[cls] = min(self._free_from[cls], old)
            self._admission.forget_etag(old)
        self._store.etags[uid] = etag
        self.uid_at[etag] = uid

    def on_holds(self, msg: p.Holds) -> None:
        """A node reports a binding it holds (SUB_AT / PUB_AT)."""
        uid, etag = msg.uid, msg.etag
        known = self._store.etags.get(uid)
        holder = self.uid_at.get(etag)
        kind = p.PUB_BIND if msg.publish else p.SUB_BIND
        if known == etag:
            if self._channels.within_limit(msg.txnode, uid):
                self._channels.use(msg.publish, uid, msg.txnode)
            return
        if (
            known is None
            and holder is None
            and etag not in self._storing
            and uid not in self._pending
        ):
            creator = self._assigned.get(msg.txnode)
            writes: list[Write] = []
            cls = sizes.size_class(etag)
            if (
                creator is None
                or not self._channels.within_limit(msg.txnode, uid)
                or not self._within_quota(writes, creator, msg.txnode, uid, cls)
            ):
                return
            self._counters["adopted"] += 1
            log.info("adopting etag %#x of channel %016x from TxNode 0x%02x", etag, uid, msg.txnode)
            self._hold(uid, etag)
            self._quota.adopt(uid, creator, cls)
            writes += [("etags", uid, etag), ("creators", uid, creator)]
            self._store.submit(writes, self._log_failure(f"adopted etag {etag:#x}"))
            self._channels.use(msg.publish, uid, msg.txnode)
            return
        self._counters["conflicts"] += 1
        self._warn("holds", "TxNode 0x%02x holds %016x at etag %#x, which contradicts the tables: "
                   "correcting", msg.txnode, uid, etag)  # fmt: skip
        self.correct(etag, uid)
        if known is None and not self._phase.recovering:  # it will ask again; answer it now
            self.on_request(p.Request(kind, msg.txnode, uid))
