"""The metrics of the ECBs (``--metrics``): the TCP-ECB's, the CAN-ECB's and its status port's,
read from their ``stats()`` (see ``ups/_metrics.py``; every one in docs/metrics.md)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ups._metrics import CAN_LINK, Metric, Reading, table

#: ``TcpEcb.stats()``
TCP_ECB = table(
    "ups_tcp_ecb",
    {
        "joined": "nodes that registered (a node back after a lost link is not counted again)",
        "left": "nodes that left: withdrew, or were silent for the liveness time",
        "pushes": "subscriber (or publisher) lists pushed to nodes after a change",
        "malformed": "links closed for a bad or unexpected frame",
        "denied": "registrations and requests refused (ACL, a wrong name, the channel limit)",
        "limited": "registrations refused because the node has MAX_CHANNELS channels",
        "impostors": "nodes refused because another identity holds their node id (TLS)",
        "identity_write_errors": "writes of the node id bindings file that failed (TLS)",
        "errors": "failures while removing a node (a bug: see the log)",
        "held_up": "liveness sweeps that came late because the event loop was held up",
        "status_builds": "status answers built",
        "status_answers": "status requests answered",
        "status_paced": "status requests that waited for the next build",
        "watch_limited": "Watches refused: the node watches 64 patterns already",
        "implied_limited": "pattern subscriptions left out: the node subscribes to 8192 "
        "channels by its patterns already",
    },
    {
        "nodes": "nodes registered",
        "watches": "patterns nodes watch for channel names",
        "channels": "channels that have a subscriber or a publisher",
        "identity_bindings": "node ids bound to the identity that first registered them (TLS)",
        "links": "TCP connections open",
    },
) + table(
    "ups_tcp_ecb_links",
    {
        "refused": "connections refused: too many links and none waiting for Hello",
        "evicted": "connections without Hello closed to make room for new ones",
        "timed_out": "connections closed for sending no Hello in time",
        "receive_refused": "frames refused before their body was read: no room left in the "
        "receive buffers",
        "receive_stalled": "links closed for holding a grown receive buffer without completing "
        "a frame in time",
    },
    {"receive_held": "bytes by which links grew their receive buffers"},
)

#: ``CanEcb.stats()``, of ``ups can-broker`` or hosted by ``ups gateway``
CAN_ECB = table(
    "ups_can_ecb",
    {
        "joined": "TxNodes assigned to joining nodes",
        "bound": "channels bound to a new etag",
        "requests": "requests from nodes (claims, bindings, holds, declarations)",
        "malformed": "management frames that could not be decoded, or declared nonsense",
        "foreign": "frames that are not UPS (11-bit, remote, error, FD management)",
        "refused": "TxNodes or etags refused because none was free",
        "admitted": "real-time streams admitted",
        "adopted": "TxNodes and bindings learned from the bus after a restart",
        "conflicts": "frames that contradicted the tables (answered with the tables' own)",
        "foreign_ecb_frames": "frames only a CAN-ECB sends, sent by another",
        "unanswered_takeovers": "times it stood by for another and took over because a request "
        "it heard had no answer (a forged Serving, or a broken CAN-ECB)",
        "unassigned": "requests from TxNodes that no node holds",
        "deferred": "binding requests deferred to the end of a recovery",
        "limited": "requests refused by a limit: channels per node, declarations per second",
        "reclaimed": "TxNodes and etags unused for the lease, given to others",
        "storage_errors": "writes to the SQLite file that failed",
        "handler_errors": "management frames whose handling failed (a bug: see the log)",
        "offers_withdrawn": "TxNodes offered to a joiner that did not claim them in time",
        "moved": "channels moved to an etag of a larger size class",
        "late_claims": "offers claimed after they had lapsed",
        "quota_hit": "bindings refused because their node id created its quota of them",
        "rosters": "Roster requests of joined nodes (a gateway that joins a running bus)",
        "roster_frames": "Uses and RosterEnd frames sent in answer to Rosters",
        "roster_replaced": "Roster requests replaced by a newer one of the same node while waiting",
        "census_censuses": "censuses of joining nodes run",
        "census_knocks": "Knocks of joining nodes heard",
        "census_queries": "census queries sent",
        "census_stages": "census answers (Stage frames) heard",
        "census_late_stages": "census answers that came after their query closed",
        "census_reopened": "census queries opened again by late answers",
        "census_incomplete": "census answers that came incomplete",
        "census_retries": "census queries asked again",
        "census_cut": "censuses cut short by their query budget",
        "storage_batches": "batches of writes to the SQLite file",
    },
    {
        "txnodes": "TxNodes assigned (in the tables)",
        "etags": "channels bound to etags (in the tables)",
        "healthy": "1 unless the SQLite file fails or another CAN-ECB serves the bus",
        "standby": "1 while another CAN-ECB serves the bus and this one stands by",
    },
)
#: what ``CanEcb.stats()`` has and ``CAN_ECB`` leaves out, and why
CAN_ECB_UNEXPOSED = {
    "storage_error": "text (ups status shows it); ups_can_ecb_healthy is 0 while it is set",
    "db": "text: the SQLite file",
    "instance": "text: this run's random instance id",
}

#: ``StatusServer.counters``: the status port of ``ups can-broker --status``
STATUS_PORT = table(
    "ups_can_ecb",
    {
        "status_refused_busy": "status connections closed unanswered: no slot came free in the "
        "5 s they waited in line",
        "status_evicted": "status connections closed because they held a slot past their turn "
        "(not asked, or not taken their answer, 0.5 s after) while others waited",
        "status_timed_out": "status connections that did not ask within 2 s of being let in, or "
        "were not answered within 5 s",
        "status_bad_requests": "status connections that sent something else than a request",
        "status_builds": "status answers built",
        "status_answers": "status requests answered",
        "status_paced": "status requests that waited for the next build",
    },
    {},
)


def tcp_ecb_reading(stats: dict[str, int]) -> Reading:
    """``stats``: ``TcpEcb.stats()``."""
    return [(TCP_ECB, stats, {})]


def can_ecb_reading(
    stats: dict[str, Any], link: Mapping[str, int], status: Mapping[str, int] | None
) -> Reading:
    """``stats``: ``CanEcb.stats()``; ``link``: its ``CanLink.stats()``; ``status``: its status
    port's ``StatusServer.counters`` (None: it has none)."""
    reading: list[tuple[list[Metric], dict[str, object], dict[str, str]]] = [
        (CAN_ECB, stats, {}),
        (CAN_LINK, dict(link), {}),
    ]
    if status is not None:
        reading.append((STATUS_PORT, dict(status), {}))
    return reading
