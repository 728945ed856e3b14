"""UPS: the Ulm Publisher/Subscriber protocol, one API across CAN buses and TCP/IP.

The whole public API is here; modules whose names start with ``_`` are internals.
"""

from ._blocking import BlockingNode, BlockingSubscription
from ._channel import Channel, ChannelLike, name_to_uid, parse_channel
from ._errors import (
    AccessDenied,
    BrokerUnavailable,
    Closed,
    ConfigError,
    DecodeError,
    Exhausted,
    PayloadTooLarge,
    Unschedulable,
    UpsError,
)
from ._message import Message
from ._node import Node, Subscription
from ._tcplink import Overflow
from ._tls import Tls

__all__ = [
    "AccessDenied",
    "BlockingNode",
    "BlockingSubscription",
    "BrokerUnavailable",
    "Channel",
    "ChannelLike",
    "Closed",
    "ConfigError",
    "DecodeError",
    "Exhausted",
    "Message",
    "Node",
    "Overflow",
    "PayloadTooLarge",
    "Subscription",
    "Tls",
    "Unschedulable",
    "UpsError",
    "name_to_uid",
    "parse_channel",
]
