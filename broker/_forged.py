"""What the CAN-ECB says when it hears a CAN-ECB frame it did not send (another CAN-ECB's, or a
forger's): where the frame contradicts its tables, the tables' truth, at once, so that whatever
a node took from the frame lasts only until then (docs/protocol.md, "More than one CAN-ECB, and
frames nobody should send"). A standing-by CAN-ECB corrects nothing; the election decides
whether it answers with Serving (``_election``).

| it hears | that contradicts its tables when | it sends |
| --- | --- | --- |
| Bind(etag, uid) | the etag is another UID's, or the UID has another etag | its Binds of both |
| Assign(t, id) | its table gives id another TxNode | Assign(its t, id) |
| Grant(etag, t, prio) | the stream is admitted at another priority, or not at all | its verdict |
| Refuse(etag, t, ...) | the stream is admitted | its Grant |
| TxNodesFull(id), Failed(id) | id holds a TxNode, or is offered one | Assign, or Offer again |
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from ups import _canproto as p

from ._admission import Admission
from ._etags import Etags
from ._txnodes import TxNodes

log = logging.getLogger("ups.can_ecb")


class Corrections:
    """Corrects frames of other CAN-ECBs by the tables of ``etags``, ``txnodes`` and
    ``admission``; each correction is counted in ``counters["conflicts"]`` and logged by
    ``warn`` (rate-limited)."""

    def __init__(
        self,
        *,
        etags: Etags,
        txnodes: TxNodes,
        admission: Admission,
        send: Callable[[p.Management], None],
        counters: dict[str, int],
        warn: Callable[..., None],
    ) -> None:
        self._etags = etags
        self._txnodes = txnodes
        self._admission = admission
        self._send = send
        self._counters = counters
        self._warn = warn

    def correct(self, msg: p.Management) -> None:
        truth = self._truth(msg)
        if not truth:
            self._warn("ecb", "a %s that this CAN-ECB did not send: another CAN-ECB or a "
                       "forger", type(msg).__name__)  # fmt: skip
            return
        self._counters["conflicts"] += 1
        self._warn(f"forged-{type(msg).__name__}", "a %s that this CAN-ECB did not send "
                   "contradicts its tables: correcting", msg)  # fmt: skip
        for frame in truth:
            self._send(frame)

    def _truth(self, msg: p.Management) -> list[p.Management]:
        """The frames of the tables that ``msg`` contradicts (none: it contradicts nothing)."""
        if isinstance(msg, p.Bind):
            if self._etags.uid_at.get(msg.etag) == msg.uid:
                return []
            return list(self._etags.truth(msg.etag, msg.uid))
        if isinstance(msg, p.Assign):
            txnode = self._txnodes.txnode_of(msg.node_id)
            return [p.Assign(txnode, msg.node_id)] if txnode not in (None, msg.txnode) else []
        if isinstance(msg, p.Grant | p.Refuse):
            verdict = self._admission.verdict(msg.etag, msg.txnode)
            if isinstance(verdict, p.Grant):
                return [verdict] if verdict != msg else []
            return [verdict] if isinstance(msg, p.Grant) else []
        if isinstance(msg, p.TxNodesFull):
            return self._txnodes.truth(msg.node_id)
        if isinstance(msg, p.Failed):  # a node id's, or a UID's (the node asks again)
            return self._txnodes.truth(msg.value)
        return []
