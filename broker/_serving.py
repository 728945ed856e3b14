"""A standalone CAN-ECB daemon's run, the same for ours (``can_ecb.serve``) and the C one
(``c_ecb.serve``): the bus's link, the status port, the metrics, and an orderly end."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

from ups._canlink import CanLink


class _Served(Protocol):
    link: CanLink

    async def start(self) -> None: ...
    def close(self) -> None: ...
    def stats(self) -> dict[str, Any]: ...
    def status(self) -> dict[str, Any]: ...


Ecb = TypeVar("Ecb", bound=_Served)


async def run(
    bus: str, make: Callable[[CanLink], Ecb], job: str, status: str | None, metrics: str | None
) -> Ecb:
    """Open ``bus``, make the CAN-ECB on it and serve it until cancelled (SIGTERM or SIGINT:
    the way to stop), with ``status`` (HOST:PORT) its tables served to ``ups status`` and
    ``ups ls``, with ``metrics`` its counters to Prometheus as ``job``. Returns the CAN-ECB,
    closed with its link, so the caller can tell how the run went."""
    from ups._metrics import Reading, serving_metrics

    from ._metrics import can_ecb_reading
    from ._status import StatusServer

    link = CanLink.open(bus)
    try:
        ecb = make(link)
    except BaseException:
        link.close()
        raise
    server = None if status is None else StatusServer(status, ecb.status)

    def reading() -> Reading:
        counters = None if server is None else server.counters
        return can_ecb_reading(ecb.stats(), ecb.link.stats(), counters)

    try:
        if server is not None:
            await server.start()
        async with serving_metrics(metrics, job, reading):
            await ecb.start()
            await asyncio.Event().wait()
    except asyncio.CancelledError:
        pass
    finally:
        if server is not None:
            await server.close()
        ecb.close()
        link.close()
    return ecb
