"""Event Channel Brokers: the CAN-ECB (TxNodes, etags) and the TCP/IP-ECB (subscription lists).

The daemons are ``ups can-broker`` and ``ups broker``. A program may also host one in its own
event loop, the only way for a python-can ``virtual`` bus (it exists inside one process)::

    async with broker.hosted_can_ecb("virtual:demo"), Node(can="virtual:demo") as node:
        ...
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # loaded on first use: a TCP-ECB does not load python-can
    from .can_ecb import CanEcb
    from .tcp_ecb import TcpEcb

__all__ = ["CanEcb", "TcpEcb", "hosted_can_ecb", "hosted_tcp_ecb"]


def __getattr__(name: str) -> Any:
    module = {"CanEcb": ".can_ecb", "TcpEcb": ".tcp_ecb"}.get(name)
    if module is None:
        raise AttributeError(f"module 'broker' has no attribute {name!r}")
    return getattr(importlib.import_module(module, __name__), name)


@contextlib.asynccontextmanager
async def hosted_can_ecb(
    bus: str, db: str | Path | None = None, **options: Any
) -> AsyncIterator[CanEcb]:
    """Serve ``bus`` (``INTERFACE:CHANNEL[,key=value...]``) as its CAN-ECB until the block ends.

    ``db`` is its SQLite file (default: the bus's own, as ``ups can-broker``); ``options`` are
    ``CanEcb``'s (``bitrate``, ``recovery``, ``lease``, ``max_channels``, ``quota``).
    """
    from ups._canlink import CanLink

    from ._store import default_db
    from .can_ecb import CanEcb

    link = CanLink.shared(bus)  # the nodes of this loop on the same bus use it too
    try:
        ecb = CanEcb(link, db if db is not None else default_db(bus), **options)
    except BaseException:
        link.release()
        raise
    try:
        await ecb.start()
        yield ecb
    finally:
        ecb.close()
        link.release()


@contextlib.asynccontextmanager
async def hosted_tcp_ecb(listen: str = "127.0.0.1:0", **options: Any) -> AsyncIterator[TcpEcb]:
    """Serve a TCP/IP network as its TCP-ECB on ``listen`` (port 0: any; see ``.port``) until
    the block ends; ``options`` are ``TcpEcb``'s (``liveness``, ``recovery``, ``tls``, ``acl``)."""
    from ups._address import parse_address

    from .tcp_ecb import TcpEcb

    host, port = parse_address(listen)
    ecb = TcpEcb(host, port, **options)
    await ecb.start()
    try:
        yield ecb
    finally:
        await ecb.close()
