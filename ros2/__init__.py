"""UPS channels as ROS 2 topics through rmw_zenoh, with nothing of ROS installed.

``ups ros2`` (``_serve``) runs a ``RosBridge`` (``_bridge``): a UPS node on any network that is
also a participant of a ROS 2 system using rmw_zenoh, following its conventions (``_rmw``:
key expressions, liveliness tokens, GIDs, attachments) and serializing messages in CDR
(``_cdr``) from definitions rosbags provides (``_types``). Which channel stands for which
topic, field by field, is the map (``_mapping``), compiled once at start (``_topic``).
docs/ros2.md describes all of it byte by byte.
"""

from ._cdr import CdrError, Codec
from ._mapping import Bridge, MapError, load_map
from ._rmw import (
    RMW_ZENOH_COMMIT,
    Qos,
    attachment,
    dds_type_name,
    entity_token,
    gid,
    node_token,
    read_attachment,
    topic_key,
)
from ._topic import TopicMap, Unrepresentable
from ._types import Types

__all__ = [
    "RMW_ZENOH_COMMIT",
    "Bridge",
    "CdrError",
    "Codec",
    "MapError",
    "Qos",
    "TopicMap",
    "Types",
    "Unrepresentable",
    "attachment",
    "dds_type_name",
    "entity_token",
    "gid",
    "load_map",
    "node_token",
    "read_attachment",
    "topic_key",
]
