"""``ups gateway``: run a ``Gateway`` until cancelled, its counters served to Prometheus with
``--metrics`` (``_metrics``)."""

from __future__ import annotations

import asyncio
import logging

from ._gateway import Gateway

log = logging.getLogger("ups.gateway")


async def serve(gateway: Gateway, metrics: str | None = None) -> None:
    """Run ``gateway`` until cancelled; log its counters when it stops. With ``metrics``
    (HOST:PORT), its counters are served there to Prometheus."""
    from ups._metrics import Reading, serving_metrics

    from ._metrics import gateway_reading

    def reading() -> Reading:
        can, ip, link, ecb = gateway.can, gateway.ip, gateway.link, gateway.can_ecb
        return gateway_reading(
            gateway.side,
            gateway.stats(),
            can=None if can is None else can.stats(),
            ip=None if ip is None else ip.stats(),
            link=None if link is None else link.stats(),
            can_ecb=None if ecb is None else ecb.stats(),
        )

    async with serving_metrics(metrics, "gateway", reading), gateway:
        try:
            await asyncio.Event().wait()
        finally:
            log.info("gateway stopping: %s", gateway.stats())
