"""A node registered with the TCP-ECB: the record the registry (``tcp_ecb``), its liveness sweep
(``_liveness``) and its Status (``_tcpstatus``) all read."""

from __future__ import annotations

import time

from ups import _tcpwire as w
from ups._tcplink import Link
from ups._tls import identity


class Member:
    """A registered node."""

    __slots__ = (
        "address", "heard", "identity", "link", "name", "node_id", "pubs", "stale", "subs",
    )  # fmt: skip

    def __init__(self, hello: w.Hello, link: Link) -> None:
        self.node_id = hello.node_id
        self.name = hello.name
        self.identity = identity(link.transport)  # None without TLS
        self.address = (hello.host, hello.port)
        self.link: Link | None = link
        self.subs: set[int] = set()
        self.pubs: set[int] = set()
        self.stale: set[tuple[bool, int]] | None = None  # registrations awaiting renewal
        self.heard = time.monotonic()

    def peer(self) -> w.Peer:
        return w.Peer(self.node_id, *self.address, self.identity)
