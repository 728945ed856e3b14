"""rmw_zenoh's conventions, as pure functions: the key expression of a topic's data, the
liveliness tokens of a node and of its publishers and subscriptions (with their compact QoS
chunk), the GID of an entity and the attachment of every sample.

Taken from ``docs/design.md`` of ros2/rmw_zenoh at ``RMW_ZENOH_COMMIT`` (and, for what the
document leaves to its code, the functions it names: ``qos_to_keyexpr``, ``mangle_name``,
``Entity``'s GID, ``AttachmentData``). docs/ros2.md shows each byte; tests/test_ros2_rmw.py
reproduces the document's examples with these builders.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

#: the rmw_zenoh commit whose docs/design.md these conventions were taken from
RMW_ZENOH_COMMIT = "99a6a2bd10b949052f4f12c5854825dc005e95a5"
ADMIN_SPACE = "@ros2_lv"  #: the hermetic first chunk of every liveliness token
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"  #: entity kinds in a token
NO_TYPE_HASH = "TypeHashNotSupported"  #: the type hash of distributions before Iron (Humble)
GID_SIZE = 16
#: sequence number (int64 LE), source time (int64 LE, ns since the epoch), the GID's length
#: (one byte: 16) and the GID
ATTACHMENT = struct.Struct("<qqB16s")

# rmw/types.h's enumerations, as the QoS chunk writes them
RELIABILITY = {"reliable": 1, "best_effort": 2}
DURABILITY = {"volatile": 2}  # transient_local (1) is not offered: no publication cache here
HISTORY = {"keep_last": 1, "keep_all": 2}


@dataclass(frozen=True, slots=True)
class Qos:
    """The QoS of a publisher or subscription: rmw_zenoh's default is reliable, volatile,
    keep last 42 (deadline, lifespan and liveliness always at their defaults here)."""

    reliability: int = 1
    durability: int = 2
    history: int = 1
    depth: int = 42

    def chunk(self) -> str:
        """The compact form in a liveliness token (``qos_to_keyexpr``): each value only where it
        differs from the default, ``reliability:durability:history,depth:deadline s,ns:lifespan
        s,ns:liveliness kind,lease s,ns``."""
        default = Qos()

        def differs(value: int, base: int) -> str:
            return "" if value == base else str(value)

        return (
            f"{differs(self.reliability, default.reliability)}:"
            f"{differs(self.durability, default.durability)}:"
            f"{differs(self.history, default.history)},{differs(self.depth, default.depth)}"
            ":,:,:,,"
        )


#: the two QoS profiles a map names (rclpy's ``qos_profile_system_default`` is keep last 10 in
#: rmw_zenoh; ``qos_profile_sensor_data``: best effort, keep last 5)
PROFILES = {"default": Qos(depth=10), "sensor_data": Qos(reliability=2, depth=5)}


def mangle(name: str) -> str:
    """A name as a single chunk: each ``/`` becomes ``%``."""
    return name.replace("/", "%")


def dds_type_name(ros_type: str) -> str:
    """``std_msgs/msg/String`` as rmw_zenoh names it: ``std_msgs::msg::dds_::String_``."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def strip_slashes(name: str) -> str:
    """``name`` less one leading and one trailing ``/``."""
    start = 1 if name.startswith("/") else 0
    end = len(name) - 1 if name.endswith("/") and len(name) > start else len(name)
    return name[start:end]


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression a topic's samples are put on:
    ``<domain>/<topic without its leading and trailing /><type name>/<type hash>``."""
    return f"{domain}/{strip_slashes(topic)}/{dds_type_name(ros_type)}/{type_hash}"


def _token(parts: list[str]) -> str:
    """The chunks joined by ``/``, up to the first empty one (as rmw_zenoh's ``Entity``)."""
    taken = []
    for part in parts:
        if not part:
            break
        taken.append(part)
    return "/".join(taken)


def node_token(
    domain: int, zid: str, node_id: int, namespace: str, name: str, enclave: str = "/"
) -> str:
    """The liveliness token of a node:
    ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<name>``."""
    return _token([ADMIN_SPACE, str(domain), zid, str(node_id), str(node_id), NODE,
                   mangle(enclave), mangle(namespace), mangle(name)])  # fmt: skip


def entity_token(
    domain: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: str,
    namespace: str,
    node: str,
    topic: str,
    ros_type: str,
    type_hash: str,
    qos: Qos,
    enclave: str = "/",
) -> str:
    """The liveliness token of a publisher (``MP``) or subscription (``MS``): the node's
    chunks, then the mangled topic, the type name, the type hash and the QoS chunk."""
    return _token([
        ADMIN_SPACE, str(domain), zid, str(node_id), str(entity_id), kind, mangle(enclave),
        mangle(namespace), mangle(node), mangle(topic), mangle(dds_type_name(ros_type)),
        mangle(type_hash), qos.chunk(),
    ])  # fmt: skip


def gid(token: str) -> bytes:
    """An entity's GID: XXH3-128 of its liveliness token, the low 64 bits then the high 64,
    each little-endian (rmw_zenoh copies the hash's two halves in memory, on little-endian
    machines)."""
    import xxhash

    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def attachment(sequence: int, source_time_ns: int, entity_gid: bytes) -> bytes:
    """The attachment of a sample: 33 bytes."""
    return ATTACHMENT.pack(sequence, source_time_ns, GID_SIZE, entity_gid)


@dataclass(frozen=True, slots=True)
class Attachment:
    sequence: int
    source_time_ns: int
    gid: bytes


def read_attachment(data: bytes | None) -> Attachment | None:
    """The attachment's fields, or None when it is not rmw_zenoh's."""
    if data is None or len(data) != ATTACHMENT.size:
        return None
    sequence, when, size, who = ATTACHMENT.unpack(data)
    return Attachment(sequence, when, who) if size == GID_SIZE else None
