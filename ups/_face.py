"""What a node and its faces share: the channel table entry, the sink, and the face interface.

A *face* is one network as a node sees it (CAN, TCP/IP, ...). It is built with what it needs
from the node: the table of channels (UID -> ``ChannelState``) and a ``Deliver`` callback for
the events it receives. It never imports the node.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, NamedTuple, Protocol

from ._channel import Channel
from ._message import Message

DEFAULT_PRIORITY = 0x80  #: events, unless the channel's priority was set
#: what a full queue drops: the oldest event queued, or the one arriving
Overflow = Literal["drop_oldest", "drop_newest"]
OVERFLOWS: tuple[Overflow, ...] = ("drop_oldest", "drop_newest")


class Sink(Protocol):
    """Where a node delivers a channel's events: a ``Subscription``, or a gateway's forwarder."""

    def _push(self, msg: Message) -> None: ...


class ChannelState:
    """What a node knows of one channel: its local subscriptions, priority and publishing."""

    __slots__ = ("channel", "declared", "max_size", "priority", "published", "subs")

    def __init__(self, channel: Channel, priority: int) -> None:
        self.channel = channel
        self.priority = priority
        self.subs: list[Sink] = []
        self.published = False
        self.declared = False  # a real-time stream: the broker owns its priority
        self.max_size = 0  # the largest event the channel's binding carries (set by the face)


#: ``deliver(state, data, priority, source, timestamp)``: hand one received event to the
#: local subscriptions of its channel.
Deliver = Callable[[ChannelState, bytes, int, int | None, float], None]
#: ``found(channel)``: a face learnt of a named channel that a watched pattern may match
Found = Callable[[Channel], None]


class FaceContext(NamedTuple):
    """What a node hands the face it builds (each face module has
    ``build(where, context, **options) -> Face`` and the set ``OPTIONS`` it accepts)."""

    node_id: int
    name: str
    deliver: Deliver
    channels: dict[int, ChannelState]
    node_stats: Callable[[], dict[str, int]]
    join_timeout: float | None


class Face(Protocol):
    """One network as seen by a node. A face calls its ``Deliver`` for each event it receives."""

    max_payload: int
    where: str  #: what the node joins, for messages ("the TCP-ECB at 10.0.0.1:7411")

    async def start(self) -> None: ...
    async def close(self) -> None: ...
    async def bind(self, state: ChannelState, subscribe: bool, size: int = 0) -> None:
        """Make ``state``'s channel usable: to publish on it (events of up to ``size`` bytes
        expected), or (``subscribe``) to receive it. Sets ``state.max_size``."""

    async def grow(self, state: ChannelState, size: int) -> None:
        """Make the channel carry events of ``size`` bytes (raise ``PayloadTooLarge`` if the
        network cannot)."""

    async def unsubscribe(self, state: ChannelState) -> None:
        """The node's last local subscriber of the channel left."""

    def send(self, state: ChannelState, data: bytes, priority: int) -> None:
        """Publish ``data`` on the network; never blocks, counts what it must drop."""

    async def room(self, state: ChannelState) -> None:
        """Wait until ``send`` on this channel would drop nothing (backpressure)."""

    async def watch(self, pattern: str, found: Found) -> None:
        """Call ``found`` with each channel whose name the network knows and ``pattern`` (a
        glob: ``_channel``) matches: those it knows now, before returning, and those it learns
        of later, until ``unwatch``. It may also name channels that do not match (the node
        checks). Raises ``ConfigError`` where the network knows no names."""

    async def unwatch(self, pattern: str) -> None:
        """No subscription of the node watches ``pattern`` any more."""

    def stats(self) -> dict[str, int]: ...
