"""The JAUS component's metrics (``ups jaus --metrics``): its counters, its node's and, on CAN,
its CAN link's (see ``ups/_metrics.py``; every one in docs/metrics.md)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ups._errors import Closed
from ups._metrics import CAN_LINK, NODE, Metric, Reading, table

if TYPE_CHECKING:
    from ups import Node

    from ._host import JausHost

#: ``JausHost.stats()``; the list driver's counters only with a mapping that has waypoints
JAUS = table(
    "ups_jaus",
    {
        "datagrams": "UDP datagrams received",
        "received": "JAUS messages received and handed to the component",
        "malformed": "datagrams or messages that could not be decoded",
        "not_for_me": "messages for another JAUS id",
        "handler_errors": "messages whose handling failed (a bug: see the log)",
        "clients_evicted": "clients forgotten to make room (MAX_CLIENTS)",
        "clients_gone": "clients forgotten after their silence",
        "sent": "JAUS messages sent",
        "acks": "acknowledgements asked for and sent (JUDP, RA 3.3)",
        "commands": "commands carried out",
        "refused_without_control": "commands refused: the sender does not control the component",
        "refused_not_ready": "commands refused: the component is not ready",
        "refused_in_emergency": "commands refused during an emergency",
        "refused_emergency": "Set or Clear Emergency refused",
        "control_granted": "Request Control granted",
        "control_refused": "Request Control refused",
        "control_lapsed": "controls that lapsed for want of the client's messages",
        "authority_capped": "Request Control asking more authority than its address range may "
        "have (the mapping's [authority])",
        "refused_other_address": "messages refused: the controller's JAUS id from another address",
        "unserved": "messages no service of this component answers",
        "not_yet": "queries and events for reports that have no data yet",
        "replies": "replies sent",
        "pose_errors": "poses from the robot that could not be read",
        "events_created": "event subscriptions created",
        "events_refused": "event subscriptions refused",
        "events_cancelled": "event subscriptions cancelled by their clients",
        "events_expired": "event subscriptions that expired",
        "events_sent": "events sent",
        "events_coalesced": "events merged into the next due (the latest report goes)",
        "event_errors": "events whose report could not be built",
        "list_changes": "waypoint list changes",
        "list_rejected": "waypoint list changes rejected",
        "elements_refused": "waypoint list elements refused",
        "lists_executed": "waypoint lists executed",
        "list_not_executed": "requests to execute a waypoint list that were not carried out",
        "waypoints_reached": "waypoints reached",
        "lists_completed": "waypoint lists followed to their end",
        "parts_expired": "parts of multi-part messages dropped: the rest did not come in time",
        "parts_evicted": "parts of multi-part messages dropped to make room",
        "parts_duplicate": "parts of multi-part messages received twice",
        "parts_conflicting": "parts of multi-part messages that contradicted others",
        "parts_oversized": "parts of multi-part messages too large to hold",
        "parts_mismatched": "parts of multi-part messages that did not belong to one",
    },
    {
        "clients": "clients (OCUs) known",
        "events": "event subscriptions open",
    },
)


def jaus_reading(host: JausHost, node: Node, network: str) -> Reading:
    """``network``: can, tcp or zenoh (``ups._cliargs.network_choice``'s kind, broker: tcp)."""
    network = "tcp" if network == "broker" else network
    reading: list[tuple[list[Metric], dict[str, Any], dict[str, str]]] = [
        (JAUS, dict(host.stats()), {}),
        (NODE, dict(node.stats()), {"network": network}),
    ]
    try:
        face: object = node.face
    except Closed:  # not joined yet
        face = None
    link = getattr(face, "link", None) if network == "can" else None  # a CanLink
    if link is not None:
        reading.append((CAN_LINK, dict(link.stats()), {}))
    return reading
