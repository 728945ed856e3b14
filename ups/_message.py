"""The message an application receives."""

from __future__ import annotations

from typing import NamedTuple

from ._channel import Channel


class Message(NamedTuple):
    """One event received on a channel (immutable; a named tuple, the cheapest to build).

    ``timestamp`` is the receive time in seconds since the epoch (``time.time()``), taken when
    the frame reached this node (or, for a local publish, when it was published). ``source`` is
    the publisher's address on the network the event came from (its TxNode on CAN, its node id
    on TCP/IP), or ``None`` for an event published in this process.
    """

    channel: Channel
    data: bytes
    timestamp: float
    priority: int
    source: int | None = None

    @property
    def uid(self) -> int:
        return self.channel.uid
