"""What a CAN face receives besides its management frames: the acceptance filters of the etags
it receives, and events larger than one frame, reassembled from the frames of their transfers
(``_cantransfer``) and given up when those stop coming.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Collection
from typing import Any

import can

from . import _canproto as p
from . import _cantransfer as t

#: the frames of TxNode 0x7F: the CAN-ECB's, and those of nodes still joining
MGMT_FILTER = {
    "can_id": p.MGMT_TXNODE << p.TXNODE_SHIFT,
    "can_mask": p.TXNODE_MASK << p.TXNODE_SHIFT,
    "extended": True,
}


def filters(etags: Collection[int], limit: int) -> list[dict[str, Any]] | None:
    """The acceptance filters of a face that receives ``etags``: the management frames and one
    filter per etag; None (every frame, filtered in software) for more than ``limit`` etags."""
    if len(etags) > limit:
        return None
    each = [{"can_id": etag, "can_mask": p.ETAG_MASK, "extended": True} for etag in etags]
    return [MGMT_FILTER, *each]


class Transfers:
    """The transfers a face reassembles: ``feed`` gives a transfer's event once its last frame
    came; a transfer whose next frame is overdue (``TRANSFER_TIMEOUT``) is given up, counted in
    ``reassembler`` and logged through ``warn(key, text)``."""

    def __init__(self, warn: Callable[..., None]) -> None:
        self.reassembler = t.Reassembler()
        self._warn = warn
        self._expiry: asyncio.TimerHandle | None = None

    def feed(self, frame: can.Message, txnode: int, etag: int) -> bytes | None:
        """Take ``frame``, from ``txnode`` on ``etag``: the event it completes, or None."""
        reassembler = self.reassembler
        event = reassembler.feed(
            (txnode, etag), bytes(frame.data), frame.is_fd, t.max_size(etag), time.monotonic()
        )
        if event is None and reassembler.pending and self._expiry is None:
            self._expiry = asyncio.get_running_loop().call_later(t.TRANSFER_TIMEOUT, self._expire)
        return event

    def close(self) -> None:
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None

    def _expire(self) -> None:
        """Give up (and count) transfers whose next frame is overdue."""
        self._expiry = None
        if self.reassembler.expire(time.monotonic()):
            self._warn("transfer", "gave up CAN transfers whose frames stopped coming")
        if self.reassembler.pending:
            self._expiry = asyncio.get_running_loop().call_later(t.TRANSFER_TIMEOUT, self._expire)
