"""``ups ros2 --map FILE --ros ENDPOINT (--can BUS | --broker HOST:PORT | --zenoh ENDPOINT)``:
run a ``RosBridge`` on a node of the robot's network until a signal."""

from __future__ import annotations

import argparse
import asyncio
import logging
from typing import Any

from ups._cliargs import node_for, say
from ups._errors import Closed
from ups._metrics import CAN_LINK, NODE, Reading, serving_metrics, table

from ._bridge import RosBridge
from ._mapping import Bridge

log = logging.getLogger("ups.ros2")

#: ``RosBridge.stats()`` (every one in docs/metrics.md)
ROS2 = table(
    "ups_ros2",
    {
        "to_ros": "events of UPS channels put on their ROS 2 topics",
        "from_ros": "ROS 2 messages published on their UPS channels",
        "out_of_range": "events or messages dropped: a value the other side cannot hold",
        "malformed": "events or messages dropped: not the catalog's layout, or not CDR of the "
        "topic's type",
        "no_attachment": "ROS 2 messages without rmw_zenoh's attachment (forwarded)",
        "ros_lost": "ROS 2 messages missed: sequence numbers their publishers skipped",
        "ros_jumps": "ROS 2 sequence numbers that went back, or jumped further than their "
        "topic's max_rate could carry (a restart or a forgery; not in ros_lost)",
        "rate_limited": "ROS 2 messages dropped: above their topic's max_rate",
        "unmatched": "UPS events that came after the last ROS 2 subscriber left (dropped)",
        "reflected": "events not sent back to the network they came from",
        "rx_overflow": "ROS 2 messages dropped: too many waiting for the event loop",
        "reconcile_errors": "failures to bring a topic's forwarding in line (tried again)",
    },
    {
        "topics": "topics of the map",
        "to_ros_forwarding": "topics forwarded to ROS 2 now (a ROS 2 subscriber matches)",
        "from_ros_forwarding": "topics forwarded from ROS 2 now (subscribed on the UPS side)",
    },
)


def ros2_reading(bridge: RosBridge | None, node: Any, network: str) -> Reading:
    network = "tcp" if network == "broker" else network
    if bridge is None:
        return []
    reading: list[Any] = [(ROS2, dict(bridge.stats()), {}), (NODE, dict(node.stats()),
                                                             {"network": network})]  # fmt: skip
    try:
        face: object = node.face
    except Closed:
        face = None
    link = getattr(face, "link", None) if network == "can" else None
    if link is not None:
        reading.append((CAN_LINK, dict(link.stats()), {}))
    return reading


async def serve(args: argparse.Namespace, bridge: Bridge) -> int:
    kind, node = node_for(args, "ups-ros2")
    # --ros is checked before the node joins; the router is waited for after (args.timeout)
    ros = RosBridge(node, bridge, args.ros, args.ros_config, join_timeout=args.timeout)
    joined = False

    def reading() -> Reading:
        return ros2_reading(ros if joined else None, node, kind)

    async with serving_metrics(getattr(args, "metrics", None), "ros2", reading), node:
        joined = True
        try:
            await ros.start()
            name = f"{bridge.namespace.rstrip('/')}/{bridge.node}"
            say(args, f"ROS 2 node {name} on {args.ros} (domain {bridge.domain}, "
                f"{bridge.distro}): {len(bridge.topics)} topics")  # fmt: skip
            await asyncio.Event().wait()
        finally:
            await ros.close()
            log.info("ups ros2 stopping: %s", ros.stats())
    return 0
