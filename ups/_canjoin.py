"""A node's side of the census: how a node without a TxNode gets one (docs/protocol.md).

The node sends Knock. To the CAN-ECB's Census it answers with all 16 nibbles of its id, one
data-less Stage frame each; to a Query whose prefix its id starts with, with the nibbles after
the prefix. When the CAN-ECB offers it a TxNode (Offer), it claims it (CLAIM from that TxNode)
and is joined when an Assign names its id.

A Stage frame it already heard from another joiner in answer to the same query is left out:
on a real bus identical frames merge, and this does the same on buses that do not (emulated
ones, or several nodes of one process). It knocks again when, for 0.3 s (doubling with each
Knock up to 2 s), it has neither knocked nor heard a Knock, Census, Query or Offer (another
joiner's Knock is the same frame as its own: on a real bus they merge); at once when a CAN-ECB
says Hello; and it gives up after ``timeout``.

TxNodesFull or Failed with its id does not end the join at once: anyone can send them. It ends
the join only once it has stood ``REFUSAL_WAIT`` seconds (counted again from each Hello, Census
or Query heard meanwhile: a census is under way, whose Offer may follow) with no Offer or Assign
of its id, which contradicts it; meanwhile the node answers as always but does not knock (a
census it started would answer it anew).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from . import _canproto as p
from ._canbinding import REFUSAL_WAIT
from ._errors import BrokerUnavailable, Exhausted

KNOCK_FIRST = 0.3  #: seconds without a Knock sent or a Census, Query or Offer heard ...
KNOCK_MAX = 2.0  #: ... before knocking again; doubling with each Knock up to this
#: Stage frames heard this recently belong to the current query of their epoch (the CAN-ECB
#: does not reuse an epoch within 250 ms)
_FRESH = 0.1


class Joiner:
    """Joins one node: ``await run()`` returns its TxNode; feed it frames with ``on_frame``."""

    def __init__(
        self, node_id: int, send: Callable[[p.Management], None], bus: str, timeout: float | None
    ) -> None:
        self.node_id = node_id
        self._nibbles = p.nibbles_of(node_id)
        self._send = send
        self._bus = bus
        self._timeout = timeout
        self._result: asyncio.Future[int] | None = None
        self._delay = KNOCK_FIRST
        self._quiet_since = 0.0  # when this node last knocked or heard Census, Query or Offer
        #: epoch -> (when last heard, {stage << 4 | nibble}): Stage frames of other joiners
        self._sent_by_others: dict[int, tuple[float, set[int]]] = {}
        self.stages_sent = 0
        #: a TxNodesFull or Failed of this id, nothing contradicted yet: since when (counted
        #: again from each Hello, Census or Query), and the error it ends the join with
        self._refusal: tuple[float, Exception] | None = None
        self.refusals = 0  #: TxNodesFull and Failed of this id heard while joining

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        self._result = result = loop.create_future()
        deadline = None if self._timeout is None else loop.time() + self._timeout
        self._delay = KNOCK_FIRST
        self._refusal = None
        self._knock()
        while True:
            refusal = self._refusal
            if refusal is None:
                wait = max(0.005, self._quiet_since + self._delay - loop.time())
            else:
                wait = max(0.005, refusal[0] + REFUSAL_WAIT - loop.time())
            if deadline is not None:
                wait = min(wait, max(0.0, deadline - loop.time()))
            try:
                return await asyncio.wait_for(asyncio.shield(result), wait)
            except TimeoutError:
                if result.done():  # the answer was an error (BrokerUnavailable is a TimeoutError)
                    return int(result.result())
            now = loop.time()
            refusal = self._refusal
            if refusal is not None and (
                now >= refusal[0] + REFUSAL_WAIT or (deadline is not None and now >= deadline)
            ):
                raise refusal[1]  # it stood: the CAN-ECB's answer
            if deadline is not None and now >= deadline:
                raise BrokerUnavailable(
                    f"no CAN-ECB gave this node a TxNode on {self._bus} within "
                    f"{self._timeout:g} s; start one with 'ups can-broker --can ...' or a gateway"
                )
            if refusal is None and now - self._quiet_since >= self._delay:  # nothing for a
                self._knock()  # while: knock again
                self._delay = min(self._delay * 2, KNOCK_MAX)

    def _knock(self) -> None:
        self._quiet_since = asyncio.get_running_loop().time()
        self._send(p.Knock())

    def on_frame(self, msg: p.Management) -> None:
        result = self._result
        if result is None or result.done():
            return
        if isinstance(msg, p.Census | p.Query | p.Hello) and self._refusal is not None:
            self._refusal = (asyncio.get_running_loop().time(), self._refusal[1])  # at work
        if isinstance(msg, p.Census):
            self._heard()
            self._burst(msg.epoch, 0)
        elif isinstance(msg, p.Hello):  # a CAN-ECB has just started: it takes knocks at once
            self._knock()
        elif isinstance(msg, p.Knock):  # another joiner's: the same frame as ours would be
            self._quiet_since = asyncio.get_running_loop().time()
        elif isinstance(msg, p.Query):
            self._heard()
            if self._nibbles[: len(msg.prefix)] == msg.prefix:
                self._burst(msg.epoch, len(msg.prefix))
        elif isinstance(msg, p.Offer) and msg.node_id == self.node_id:
            self._heard()
            self._refusal = None  # contradicted: a TxNode for it after all
            self._send(p.Request(p.CLAIM, msg.txnode, self.node_id))
        elif isinstance(msg, p.Assign) and msg.node_id == self.node_id:
            result.set_result(msg.txnode)
        elif isinstance(msg, p.TxNodesFull) and msg.node_id == self.node_id:
            self._refused(Exhausted(f"all {p.TXNODE_COUNT} TxNodes of {self._bus} are taken"))
        elif isinstance(msg, p.Failed) and msg.value == self.node_id:
            self._refused(
                BrokerUnavailable(
                    f"the CAN-ECB of {self._bus} could not store this node's TxNode: its "
                    "database fails (see its log and 'ups status')"
                )
            )

    def _refused(self, error: Exception) -> None:
        """TxNodesFull or Failed of this id: the end of the join if nothing contradicts it."""
        self.refusals += 1
        if self._refusal is None:
            self._refusal = (asyncio.get_running_loop().time(), error)
        else:  # the first one's time, the latest one's error
            self._refusal = (self._refusal[0], error)

    def _heard(self) -> None:
        """The CAN-ECB is at work on the census: no knock needed for a while."""
        self._quiet_since = asyncio.get_running_loop().time()
        self._delay = KNOCK_FIRST

    def heard_stage(self, arg: int) -> None:
        """Another joiner sent Stage with this 12-bit argument (epoch, stage, nibble). It may
        come before this node saw the query itself (another node of the process answered
        first)."""
        now = time.monotonic()
        epoch = arg >> 8
        seen = self._sent_by_others.get(epoch)
        if seen is None or now - seen[0] > _FRESH:
            seen = self._sent_by_others[epoch] = (now, set())
        seen[1].add(arg & 0xFF)

    def _burst(self, epoch: int, start: int) -> None:
        seen = self._sent_by_others.get(epoch)
        fresh = seen is not None and time.monotonic() - seen[0] <= _FRESH
        heard = seen[1] if seen is not None and fresh else set()
        for stage in range(start, p.NIBBLES):
            if (stage << 4 | self._nibbles[stage]) not in heard:
                self._send(p.Stage(epoch, stage, self._nibbles[stage]))
                self.stages_sent += 1
