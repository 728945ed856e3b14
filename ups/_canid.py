"""UPS on CAN: the 29-bit identifier: its fields, the values reserved in them, and pure functions
to pack and unpack it.

An identifier is ``priority (8) | TxNode (7) | etag (14)``, priority most significant so that
CAN arbitration follows it. A frame is *management* when its priority is below
``FIRST_EVENT_PRIORITY``, its TxNode is ``MGMT_TXNODE`` (the CAN-ECB, and nodes still without
a TxNode) or its etag is below ``FIRST_ETAG``; every other 29-bit frame is an *event* on the
channel bound to its etag. A node's 64-bit id travels nibble by nibble while it joins.
``docs/protocol.md`` describes the same layout bit by bit; keep them in step. The management
frames themselves are ``_canproto``'s.
"""

from __future__ import annotations

PRIORITY_SHIFT = 21
TXNODE_SHIFT = 14
ETAG_MASK = 0x3FFF
TXNODE_MASK = 0x7F
PRIORITY_MASK = 0xFF

MGMT_TXNODE = 0x7F  #: the CAN-ECB's frames and those of nodes still joining
TXNODE_COUNT = 127  #: TxNodes 0x00..0x7E are given to nodes
FIRST_ETAG = 0x0010  #: etags 0x0000..0x000F are reserved for management
LAST_ETAG = 0x3FFF
CONFIG_PRIORITY = 0x00  #: configuration frames, node requests, SUB_AT
BIND_PRIORITY = 0x01  #: Bind from the CAN-ECB, PUB_AT from nodes
FIRST_EVENT_PRIORITY = 0x02  #: events use 0x02..0xFF
NIBBLES = 16  #: a 64-bit node id is offered nibble by nibble, most significant first
CLASSIC_MAX_DATA = 8
LARGE_FIRST_ETAG = 0x3000  #: etags from here carry events larger than one frame (_cantransfer)


def make_id(priority: int, txnode: int, etag: int) -> int:
    """Pack the three fields into a 29-bit identifier."""
    return (priority << PRIORITY_SHIFT) | (txnode << TXNODE_SHIFT) | etag


def split_id(can_id: int) -> tuple[int, int, int]:
    """Unpack a 29-bit identifier into ``(priority, txnode, etag)``."""
    return (
        (can_id >> PRIORITY_SHIFT) & PRIORITY_MASK,
        (can_id >> TXNODE_SHIFT) & TXNODE_MASK,
        can_id & ETAG_MASK,
    )


def is_management(can_id: int) -> bool:
    return (
        (can_id >> PRIORITY_SHIFT) & PRIORITY_MASK < FIRST_EVENT_PRIORITY
        or ((can_id >> TXNODE_SHIFT) & TXNODE_MASK) == MGMT_TXNODE
        or (can_id & ETAG_MASK) < FIRST_ETAG
    )


def nibbles_of(node_id: int) -> tuple[int, ...]:
    """The 16 nibbles of a 64-bit node id, most significant first."""
    return tuple((node_id >> (4 * (NIBBLES - 1 - i))) & 0xF for i in range(NIBBLES))


def id_of(nibbles: tuple[int, ...]) -> int:
    """The 64-bit node id whose 16 nibbles these are."""
    value = 0
    for nib in nibbles:
        value = (value << 4) | nib
    return value
