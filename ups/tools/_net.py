"""The network a tool watches: a CAN bus, or an IP network (TCP/IP with its TCP-ECB, or Zenoh)
that it asks for its nodes and channels and joins with a node of its own."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from .._cliargs import network_choice, tls_of

if TYPE_CHECKING:
    from .._node import Node


class IpNetwork:
    """A TCP/IP network (``kind`` "broker": ``where`` is the TCP-ECB) or a Zenoh network
    (``kind`` "zenoh": ``where`` is a router's endpoint, with ``--zenoh-config``)."""

    def __init__(self, kind: str, where: str, args: argparse.Namespace) -> None:
        self.kind = kind
        self.where = where
        self.label = "tcp" if kind == "broker" else "zenoh"  #: as the live view names it
        self._config = getattr(args, "zenoh_config", None)
        self.tls = tls_of(args) if kind == "broker" else None
        self._timeout = float(args.timeout)

    def __str__(self) -> str:
        return self.where or str(self._config)

    def node(self, name: str) -> Node:
        """A node that joins the network (not started)."""
        from .._node import Node

        return Node(
            broker=self.where if self.kind == "broker" else None,
            zenoh=self.where if self.kind == "zenoh" else None,
            zenoh_config=self._config,
            tls=self.tls,
            name=name,
            join_timeout=self._timeout,
        )

    async def status(self) -> dict[str, Any]:
        """Its nodes and channels: the TCP-ECB's Status, or on Zenoh every node's, merged in
        the same shape (``nodes``, ``channels``)."""
        if self.kind == "broker":
            from .._tcpquery import query_status

            return await query_status(self.where, self._timeout, self.tls)
        from .._zenohstatus import network_status

        return await network_status(self.where, self._config, self._timeout)

    async def node_status(self, address: str) -> dict[str, Any]:
        """The status of the TCP/IP node listening at ``address`` (as ``ups status`` shows)."""
        from .._tcpquery import query_status

        return await query_status(address, self._timeout, self.tls)


def network_of(args: argparse.Namespace) -> tuple[str | None, IpNetwork | None]:
    """(the CAN bus, None) or (None, the IP network) the options or the environment name."""
    kind, where = network_choice(args)
    if kind == "can":
        return where, None
    return None, IpNetwork(kind, where, args)
