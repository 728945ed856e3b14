"""The message an application receives."""

from __future__ import annotations

from dataclasses import dataclass

from ._channel import Channel


@dataclass(frozen=True, slots=True)
class Message:
    """One event received on a channel.

    ``timestamp`` is the receive time in seconds since the epoch (``time.time()``), taken when
    the frame reached this node (or, for a local publish, when it was published). ``source`` is
    the publisher's address on the network the event came from (its TxNode on CAN), or ``None``
    for an event published in this process.
    """

    channel: Channel
    data: bytes
    timestamp: float
    priority: int
    source: int | None = None

    @property
    def uid(self) -> int:
        return self.channel.uid
