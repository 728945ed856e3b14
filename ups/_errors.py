"""The exceptions UPS raises. One root, a few subclasses named by what went wrong::

UpsError
 ├── ConfigError          bad argument: channel, bus spec, priority, node id (ValueError)
 ├── PayloadTooLarge      more data than one frame of the network carries (ValueError)
 ├── BrokerUnavailable    no Event Channel Broker answered in time (TimeoutError)
 ├── Exhausted            the broker has no TxNode / etag left to give
 ├── AccessDenied         the TCP-ECB refused: ACL, a wrong channel name, a bound
 ├── DecodeError          bytes on a link are not a valid UPS frame
 └── Closed               the node or subscription was closed
"""

from __future__ import annotations


class UpsError(Exception):
    """Root of every error raised by UPS."""


class ConfigError(UpsError, ValueError):
    """An argument is invalid: a channel name, a bus spec, a priority, a node id."""


class PayloadTooLarge(UpsError, ValueError):
    """A publish carries more data than the channel's network can carry in one frame."""


class BrokerUnavailable(UpsError, TimeoutError):
    """No Event Channel Broker answered within the time allowed."""


class Exhausted(UpsError):
    """The broker has no identifier left to give (all 127 TxNodes or all etags are bound)."""


class AccessDenied(UpsError):
    """The TCP-ECB refused a registration (or the connection itself): the identity of this
    node's certificate lacks the right in the broker's access control list, the channel's name
    is not the name of its UID, or the node registered as many channels as one node may."""

    def __init__(self, message: str, channel: str = "", right: str = "") -> None:
        super().__init__(message)
        self.channel = channel  #: the channel refused (empty when the connection was)
        self.right = right  #: "publish", "subscribe", "status" or "connect"


class Unschedulable(UpsError):
    """The CAN-ECB refused a real-time declaration: a declared channel would miss its deadline."""


class DecodeError(UpsError):
    """Bytes received from a link are not a valid UPS frame."""


class Closed(UpsError):
    """The node or subscription was closed."""
