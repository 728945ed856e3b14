"""The CAN-ECB's TxNode table: which node (64-bit id) sends under which 7-bit TxNode.

The census (``_census``) finds the ids of joining nodes; each is offered a TxNode
(``OFFER_TIMEOUT`` s to claim it), stored, then announced (Assign). A node already known gets its
own TxNode back. Claims answer the CAN-ECB's Hello: in a recovery window the TxNodes they name
are adopted when nobody else holds them, and a node that claims another's TxNode is moved. A
TxNode adopted in a later window (from a stray), or given in one to a moved id that held none,
is on probation until any frame of it comes: when none is free, the lowest TxNode on probation
is reclaimed, else the one silent longest once past the lease. See docs/protocol.md, *Joining*
and *Restarts, recovery and the answer to Hello*.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Protocol

from ups import _canproto as p

from ._store import Store, Write

log = logging.getLogger("ups.can_ecb")

OFFER_TIMEOUT = 1.0  #: an offer not claimed within this time (or longer while answers come
#: late: see ``offer_wait``) lapses: its TxNode is offered to others only when no other is free
LAPSED = 127  #: lapsed offers remembered, so that a late claim of one still gets its TxNode


class Phase(Protocol):
    """Where the CAN-ECB stands (the CAN-ECB itself): what the table may do now."""

    recovering: bool  #: in a recovery window: claims are adopted
    standby: bool  #: another CAN-ECB serves the bus: nothing is offered or assigned
    started_up: bool  #: the first recovery window is over: later ones are for strays only
    strays: set[int]  #: TxNodes heard asking while unknown, since the last Hello


class TxNodes:
    """``node_at`` (TxNode -> node id) beside the store's node id -> TxNode; ``seen`` (TxNode
    -> when its last frame came) for the lease.

    Handed the CAN-ECB's ``phase``, its ``send``, its ``counters`` (joined, adopted, conflicts,
    refused, reclaimed, offers_withdrawn are counted there), its rate-limited ``warn``, and
    ``stored``/``log_failure`` to report writes; ``forget(txnode)`` is called when a TxNode is
    (re)assigned or reclaimed (its node starts with no channels), ``unassigned(txnode)`` for a
    claim of a TxNode nobody holds outside a recovery window."""

    def __init__(
        self,
        store: Store,
        *,
        phase: Phase,
        send: Callable[[p.Management], None],
        counters: dict[str, int],
        warn: Callable[..., None],
        stored: Callable[[BaseException | None, str, int | None], bool],
        log_failure: Callable[[str], Callable[[BaseException | None], None]],
        forget: Callable[[int], None],
        unassigned: Callable[[int], None],
        lease: float,
        offer_wait: Callable[[], float] = lambda: OFFER_TIMEOUT,
    ) -> None:
        self._store = store
        self._phase = phase
        self._send = send
        self._counters = counters
        self._warn = warn
        self._stored = stored
        self._log_failure = log_failure
        self._forget = forget
        self._unassigned = unassigned
        self._lease = lease
        self._offer_wait = offer_wait
        self.node_at = {t: n for n, t in store.txnodes.items()}  # TxNode -> node id
        self._pending: dict[int, int] = {}  # node id -> TxNode being written
        self._offers: dict[int, tuple[int, asyncio.TimerHandle]] = {}  # node id -> TxNode
        self._lapsed: dict[int, int] = {}  # node id -> TxNode of an offer it did not claim in time
        self.seen = dict.fromkeys(range(p.TXNODE_COUNT), time.monotonic())
        #: TxNodes adopted from a stray's CLAIM (or given to a stray's id moved) and not heard
        #: since: reclaimed first when none is free (a forger's made-up ids go silent; a real
        #: node asks again). Soft state: not stored
        self.probation: set[int] = set()

    def heard(self, txnode: int, now: float) -> None:
        """A frame of ``txnode`` came (before it is handled): its lease starts again, and its
        probation is over."""
        self.seen[txnode] = now
        self.probation.discard(txnode)

    def close(self) -> None:
        for _, timer in self._offers.values():
            timer.cancel()
        self._offers.clear()

    def found(self, node_ids: list[int]) -> None:
        """The census found these ids: offer each a TxNode, which its node must claim."""
        for node_id in node_ids:
            if self._phase.standby or node_id in self._pending:
                continue
            offer = self._offers.get(node_id)
            txnode = offer[0] if offer else self._lapsed.pop(node_id, None)
            if txnode is None or not self._free_for(txnode, node_id):
                txnode = self._txnode_for(node_id)
            if txnode is None:
                continue
            if offer:
                offer[1].cancel()
            wait = max(OFFER_TIMEOUT, self._offer_wait())
            timer = asyncio.get_running_loop().call_later(wait, self._withdraw, node_id)
            self._offers[node_id] = (txnode, timer)
            self._send(p.Offer(txnode, node_id))

    def move(self, node_id: int, *, probation: bool = False) -> None:
        """Give a joined node whose TxNode another holds a TxNode of its own (Assign); a new one
        is on ``probation`` (a stray's id that held none, moved in a later window)."""
        txnode = self._txnode_for(node_id)
        if txnode is not None:
            self._assign(node_id, txnode, probation=probation)

    def _txnode_for(self, node_id: int) -> int | None:
        """The TxNode ``node_id`` holds, else a free one (reclaiming the one silent longest,
        past the lease), else None and TxNodesFull."""
        txnode = self._store.txnodes.get(node_id)
        if txnode is not None:
            return txnode
        writes: list[Write] = []
        txnode = self._free(writes)
        if txnode is None:
            self._counters["refused"] += 1
            log.warning("no TxNode left for node %016x", node_id)
            self._send(p.TxNodesFull(node_id))
        elif writes:  # reclaimed: its old owner is forgotten for good
            self._store.submit(writes, self._log_failure(f"the reclaim of TxNode 0x{txnode:02x}"))
        return txnode

    def _withdraw(self, node_id: int) -> None:
        """Nobody claimed the offer in time: the id was not a node's (frames were lost or late),
        or its node is slow. Remember it: a late claim still gets that TxNode if it is free."""
        offer = self._offers.pop(node_id, None)
        if offer is None:
            return
        self._counters["offers_withdrawn"] += 1
        self._lapsed.pop(node_id, None)
        self._lapsed[node_id] = offer[0]
        if len(self._lapsed) > LAPSED:
            del self._lapsed[next(iter(self._lapsed))]

    def _free_for(self, txnode: int, node_id: int) -> bool:
        """Nobody holds ``txnode`` and it is offered to nobody but ``node_id``."""
        if txnode in self.node_at or txnode in self._pending.values():
            return False
        return all(t != txnode or n == node_id for n, (t, _) in self._offers.items())

    def _assign(self, node_id: int, txnode: int, *, probation: bool = False) -> None:
        """The node claimed the TxNode offered to it (or is moved to it): store the assignment,
        then announce it. A TxNode it holds already keeps its probation."""
        if self._phase.standby or node_id in self._pending:
            return
        if self._store.txnodes.get(node_id) == txnode:
            self._assigned(node_id, txnode)
            return
        self._pending[node_id] = txnode

        def done(error: BaseException | None) -> None:
            del self._pending[node_id]
            if self._stored(error, f"TxNode {txnode} of node {node_id:016x}", node_id):
                self._hold(node_id, txnode)
                if probation:  # until its node speaks from it: a real one does at once
                    self.probation.add(txnode)
                self._assigned(node_id, txnode)

        self._store.submit([("txnodes", node_id, txnode)], done)

    def _assigned(self, node_id: int, txnode: int) -> None:
        self._counters["joined"] += 1
        self.seen[txnode] = time.monotonic()
        self._forget(txnode)  # a (re)joining node starts with no subscriptions
        log.info("node %016x has TxNode 0x%02x", node_id, txnode)
        self._send(p.Assign(txnode, node_id))

    def _free(self, writes: list[Write]) -> int | None:
        offered = {t for t, _ in self._offers.values()}
        taken = set(self.node_at) | set(self._pending.values()) | offered
        lapsed = set(self._lapsed.values())  # kept for late claims while others are free
        free = next((t for t in range(p.TXNODE_COUNT) if t not in taken | lapsed), None)
        if free is not None:
            return free
        for node_id, txnode in self._lapsed.items():  # the oldest lapsed offer first
            if txnode not in taken:
                del self._lapsed[node_id]
                return txnode
        now = time.monotonic()
        idle = [t for t in self.node_at if t not in offered]  # offered: a node's own, in use
        stray = min((t for t in idle if t in self.probation), default=None)
        if stray is not None:  # adopted from a stray's CLAIM, silent since: past its lease
            return self._reclaim(stray, writes, "on probation")
        oldest = min(idle, key=lambda t: self.seen[t], default=None)
        if oldest is None or now - self.seen[oldest] < self._lease:
            return None
        return self._reclaim(oldest, writes, f"silent for {now - self.seen[oldest]:.0f} s")

    def _reclaim(self, txnode: int, writes: list[Write], why: str) -> int:
        """Take ``txnode`` from its node, which is forgotten for good (``writes``)."""
        old_id = self.node_at.pop(txnode)
        del self._store.txnodes[old_id]
        self._lapsed.pop(old_id, None)  # a late CLAIM of it is a stranger's (as in libups-ecb)
        self.probation.discard(txnode)
        self._forget(txnode)
        writes.append(("txnodes", old_id, None))
        self._counters["reclaimed"] += 1
        log.warning("reclaimed TxNode 0x%02x of node %016x, %s", txnode, old_id, why)
        return txnode

    def _hold(self, node_id: int, txnode: int) -> None:
        self._store.txnodes[node_id] = txnode
        self.node_at[txnode] = node_id
        self.probation.discard(txnode)  # a new holder

    def txnode_of(self, node_id: int) -> int | None:
        """The TxNode the table gives ``node_id``."""
        return self._store.txnodes.get(node_id)

    def truth(self, node_id: int) -> list[p.Management]:
        """What contradicts a TxNodesFull or Failed of ``node_id``: the Assign of the TxNode it
        holds, or the Offer of the one it is offered (again); nothing while its assignment is
        being stored (the Assign follows) or when nothing is known of it."""
        if node_id in self._pending:
            return []
        txnode = self._store.txnodes.get(node_id)
        if txnode is not None:
            return [p.Assign(txnode, node_id)]
        offer = self._offers.get(node_id)
        return [p.Offer(offer[0], node_id)] if offer is not None else []

    def on_claim(self, txnode: int, node_id: int) -> None:
        offer = self._offers.get(node_id)
        if offer is not None and offer[0] == txnode:  # a joiner takes the TxNode offered
            offer[1].cancel()
            del self._offers[node_id]
            self._assign(node_id, txnode)
            return
        if self._pending.get(node_id) == txnode:  # claimed again (an Offer came twice): the
            return  # assignment is being stored, and its Assign follows
        if self._lapsed.get(node_id) == txnode and node_id not in self._store.txnodes:
            del self._lapsed[node_id]  # a joiner that was slow to claim what it was offered
            self._counters["late_claims"] += 1
            if self._free_for(txnode, node_id):
                self._assign(node_id, txnode)
            else:  # given to another meanwhile: it gets a TxNode of its own (Assign)
                self.move(node_id)
            return
        known = self._store.txnodes.get(node_id)
        if known == txnode:
            return
        holder = self.node_at.get(txnode)
        if not self._phase.recovering:  # claims answer Hello; any other is stray or forged
            self._counters["conflicts"] += 1
            self._warn("claim", "ignored CLAIM of TxNode 0x%02x by node %016x outside recovery",
                       txnode, node_id)  # fmt: skip
            if known is not None and holder is None:  # it was told to move: tell it the truth
                self._send(p.Assign(known, node_id))
            elif holder is None and known is None:
                self._unassigned(txnode)
            return
        phase = self._phase
        if phase.started_up and txnode not in phase.strays:  # later windows: for strays only
            self._counters["conflicts"] += 1
            self._warn("claim", "ignored CLAIM of TxNode 0x%02x by node %016x: it asked nothing",
                       txnode, node_id)  # fmt: skip
            return
        if known is None and holder is None and txnode not in self._pending.values():
            self._counters["adopted"] += 1
            log.info("adopting TxNode 0x%02x of node %016x", txnode, node_id)
            self._hold(node_id, txnode)
            if phase.started_up:  # a stray's: on probation until it speaks again (after this)
                self.probation.add(txnode)
            self._store.submit(
                [("txnodes", node_id, txnode)], self._log_failure(f"adopted TxNode 0x{txnode:02x}")
            )
            return
        self._counters["conflicts"] += 1
        log.warning("node %016x claims TxNode 0x%02x held by another node: moving it",
                    node_id, txnode)  # fmt: skip
        # the holder of ``txnode`` keeps it and its channels. An id that held nothing is a
        # stray's in a later window: its new TxNode is on probation, as an adopted one is (a
        # flood of CLAIMs of one TxNode by made-up ids would take every TxNode otherwise)
        self.move(node_id, probation=phase.started_up and known is None)
