"""UPS: the Ulm Publisher/Subscriber protocol, one API across CAN buses, TCP/IP and Zenoh.

The whole public API is here; modules whose names start with ``_`` are internals. Names are
loaded on first use, so a tool that needs only part of UPS (``ups --help``, a TCP/IP-only
program) does not pay for the rest (python-can, asyncio, msgpack).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
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
    from ._face import Overflow
    from ._message import Message
    from ._node import Node
    from ._subscription import Subscription
    from ._tls import Tls

_WHERE = {
    "BlockingNode": "_blocking",
    "BlockingSubscription": "_blocking",
    "Channel": "_channel",
    "ChannelLike": "_channel",
    "name_to_uid": "_channel",
    "parse_channel": "_channel",
    "AccessDenied": "_errors",
    "BrokerUnavailable": "_errors",
    "Closed": "_errors",
    "ConfigError": "_errors",
    "DecodeError": "_errors",
    "Exhausted": "_errors",
    "PayloadTooLarge": "_errors",
    "Unschedulable": "_errors",
    "UpsError": "_errors",
    "Message": "_message",
    "Node": "_node",
    "Subscription": "_subscription",
    "Overflow": "_face",
    "Tls": "_tls",
}

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
]  # the names of _WHERE


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'ups' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # once loaded, a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])
