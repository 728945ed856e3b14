"""The gateway's metrics (``ups gateway --metrics``): its forwarding, its two nodes (CAN and
the IP side), its CAN link and the CAN-ECB it hosts (see ``ups/_metrics.py``; every one in
docs/metrics.md)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ups._metrics import CAN_LINK, COUNTER, GAUGE, NODE, Metric, Reading, table
from ups.broker._metrics import CAN_ECB

#: ``Gateway.stats()`` read the same on either IP side
_COMMON = table(
    "ups_gateway",
    {
        "can_dropped": "events to CAN dropped, the oldest first, because the queue was full",
        "too_large_for_can": "events to CAN larger than a channel on the bus can carry",
        "reconcile_errors": "failures to bring a channel's forwarding in line (tried again)",
        "pacer_errors": "events to CAN whose frames could not be sent",
        "denied": "channels the TCP-ECB's ACL does not let the gateway forward",
        "tapped": "events of a new publisher kept until the gateway forwarded its channel",
        "tap_dropped": "events of a new publisher dropped: more than the tap keeps per channel",
        "tap_full": "new publishers' channels not tapped: 64 channels tapped already",
    },
    {"can_queued": "events waiting to go to CAN, paced to the bit rate"},
)


def gateway_table(side: str) -> list[Metric]:
    """``Gateway.stats()`` of a gateway whose IP side is ``side`` (tcp or zenoh)."""
    forwarded, forwarding = "ups_gateway_forwarded_total", "ups_gateway_forwarding_channels"
    return [
        Metric(forwarded, COUNTER, "events forwarded, by direction", "to_can",
               (("direction", "to_can"),)),
        Metric(forwarded, COUNTER, "events forwarded, by direction", f"to_{side}",
               (("direction", "to_ip"),)),
        Metric(forwarding, GAUGE, "channels forwarded, by direction", "forwarding_to_can",
               (("direction", "to_can"),)),
        Metric(forwarding, GAUGE, "channels forwarded, by direction", f"forwarding_to_{side}",
               (("direction", "to_ip"),)),
        *_COMMON,
    ]  # fmt: skip


#: what ``Gateway.stats()`` has and ``gateway_table`` leaves out, and why (SIDE: tcp or zenoh)
GATEWAY_UNEXPOSED = {
    "SIDE_dropped": "the IP node's peer_dropped, as ups_node_peer_dropped_total",
    "SIDE_lost": "the IP node's lost, as ups_node_lost_total",
    "can_tx_failed": "the CAN link's, as ups_can_tx_failed_total",
    "bindings": "the CAN node's, as ups_node_bindings",
    "txnode": "the CAN node's, as ups_node_txnode",
}


def gateway_reading(
    side: str,
    stats: Mapping[str, int],
    *,
    can: Mapping[str, Any] | None,
    ip: Mapping[str, Any] | None,
    link: Mapping[str, int] | None,
    can_ecb: dict[str, Any] | None,
) -> Reading:
    """A gateway's reading, from the ``stats()`` of the gateway (whose IP side is ``side``),
    its CAN and IP nodes, its CAN link and the CAN-ECB it hosts (None: it has not, or not yet)."""
    reading: list[tuple[list[Metric], dict[str, Any], dict[str, str]]] = [
        (gateway_table(side), dict(stats), {})
    ]
    if can is not None:
        reading.append((NODE, dict(can), {"network": "can"}))
    if ip is not None:
        reading.append((NODE, dict(ip), {"network": side}))
    if link is not None:
        reading.append((CAN_LINK, dict(link), {}))
    if can_ecb is not None:
        reading.append((CAN_ECB, can_ecb, {}))
    return reading
