"""UPS on CAN: the 29-bit identifier layout and the management frames, as pure codecs.

No I/O here. ``docs/protocol.md`` describes the same layout byte by byte; keep them in step.

An identifier is ``priority (8) | TxNode (7) | etag (14)``, priority most significant so that
CAN arbitration follows it. A frame is *management* when its TxNode is ``MGMT_TXNODE`` (the
CAN-ECB and nodes still without a TxNode) or its etag is below ``FIRST_ETAG``; every other
29-bit frame is an *event* on the channel bound to its etag.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from ._errors import DecodeError

PRIORITY_SHIFT = 21
TXNODE_SHIFT = 14
ETAG_MASK = 0x3FFF
TXNODE_MASK = 0x7F
PRIORITY_MASK = 0xFF

MGMT_TXNODE = 0x7F  #: the CAN-ECB's frames and those of nodes still joining
TXNODE_COUNT = 127  #: TxNodes 0x00..0x7E are given to nodes
FIRST_ETAG = 0x0010  #: etags 0x0000..0x000F are reserved for management
LAST_ETAG = 0x3FFF
CONFIG_PRIORITY = 0x00  #: configuration frames and node requests
BIND_PRIORITY = 0x01  #: binding announcements from the CAN-ECB
DEFAULT_PRIORITY = 0x80  #: events, unless the channel's priority was set
NIBBLES = 16  #: a 64-bit node id is raced nibble by nibble, most significant first
EPOCHS = 16
CLASSIC_MAX_DATA = 8


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
    return ((can_id >> TXNODE_SHIFT) & TXNODE_MASK) == MGMT_TXNODE or (
        can_id & ETAG_MASK
    ) < FIRST_ETAG


def nibbles_of(node_id: int) -> tuple[int, ...]:
    """The 16 nibbles of a 64-bit node id, most significant first."""
    return tuple((node_id >> (4 * (NIBBLES - 1 - i))) & 0xF for i in range(NIBBLES))


# --- configuration: the TxNode race (priority 0x00, TxNode 0x7F, etag field = op | arg) ------

_OP_STAGE, _OP_ACK, _OP_ASSIGN, _OP_STATUS = 0, 1, 2, 3
_ST_RESET, _ST_TXNODES_FULL, _ST_ETAGS_FULL, _ST_HELLO, _ST_GRANT, _ST_REFUSE = range(6)


@dataclass(frozen=True, slots=True)
class Stage:
    """A joining node offers the nibble of its node id at ``stage``, given the ECB's ``epoch``."""

    epoch: int
    stage: int
    nibble: int


@dataclass(frozen=True, slots=True)
class Ack:
    """The CAN-ECB's race state: the winning prefix so far, and the epoch it is valid in."""

    epoch: int
    prefix: tuple[int, ...]  # 1..16 nibbles


@dataclass(frozen=True, slots=True)
class Assign:
    """The CAN-ECB gives ``txnode`` to the node whose 64-bit id is ``node_id``."""

    txnode: int
    node_id: int


@dataclass(frozen=True, slots=True)
class Reset:
    """The CAN-ECB starts a race with an empty prefix in ``epoch`` (also sent when it starts)."""

    epoch: int


@dataclass(frozen=True, slots=True)
class Hello:
    """The CAN-ECB has just started; configured nodes announce their TxNode and channels again."""

    epoch: int


@dataclass(frozen=True, slots=True)
class TxNodesFull:
    """No TxNode is left for ``node_id``."""

    node_id: int


@dataclass(frozen=True, slots=True)
class EtagsFull:
    """No etag is left for channel ``uid``."""

    uid: int


@dataclass(frozen=True, slots=True)
class Grant:
    """The real-time stream of ``txnode`` on ``etag`` is admitted and sent at ``priority``."""

    etag: int
    txnode: int
    priority: int


@dataclass(frozen=True, slots=True)
class Refuse:
    """A declaration on ``etag`` by ``txnode`` is refused: with it, the stream of ``miss_txnode``
    on ``miss_etag`` would miss its deadline (worst-case response ``response_10us`` x 10 us,
    ``RESPONSE_UNBOUNDED`` when the analysis finds no bound or it does not fit 16 bits)."""

    etag: int
    txnode: int
    miss_etag: int
    miss_txnode: int
    response_10us: int


RESPONSE_UNBOUNDED = 0xFFFF
TIME_UNIT_US = 100  #: declared periods, deadlines and jitters are multiples of 100 us

# --- binding (priority 0x01, TxNode 0x7F, etag field = the bound etag) ----------------------


@dataclass(frozen=True, slots=True)
class Bind:
    """The CAN-ECB announces that channel ``uid`` uses ``etag`` on this bus."""

    etag: int
    uid: int


# --- node requests (priority 0x00, the node's TxNode, a reserved etag) ---------------------

PUB_BIND = 0x0001  #: bind a channel to publish on it
SUB_BIND = 0x0002  #: bind a channel and subscribe to it
UNSUB = 0x0003  #: the node's last subscriber of the channel left
CLAIM = 0x0004  #: "I hold this TxNode": sent after a CAN-ECB (re)start
DECLARE = 0x0005  #: a real-time declaration (see Declare)
_REQUEST_KINDS = (PUB_BIND, SUB_BIND, UNSUB, CLAIM)


@dataclass(frozen=True, slots=True)
class Request:
    """A configured node's request; ``value`` is a channel UID, or the node id for CLAIM."""

    kind: int
    txnode: int
    value: int


@dataclass(frozen=True, slots=True)
class Declare:
    """``txnode`` publishes on ``etag`` at most one frame of ``size_bytes`` every ``period``,
    released up to ``jitter`` late, due within ``deadline``; all in units of 100 us."""

    txnode: int
    etag: int
    size_bytes: int
    period: int  # 1..65535
    deadline: int  # 1..65535
    jitter: int  # 0..255


Management = (
    Stage
    | Ack
    | Assign
    | Reset
    | Hello
    | TxNodesFull
    | EtagsFull
    | Grant
    | Refuse
    | Bind
    | Request
    | Declare
)


def encode(msg: Management) -> tuple[int, bytes]:
    """The ``(arbitration_id, data)`` of a management frame."""
    if isinstance(msg, Stage):
        arg = (msg.epoch << 8) | (msg.stage << 4) | msg.nibble
        return _config_id(_OP_STAGE, arg), b""
    if isinstance(msg, Ack):
        n = len(msg.prefix)
        value = 0
        for nib in msg.prefix:
            value = (value << 4) | nib
        value <<= 4 * (NIBBLES - n)
        arg = (msg.epoch << 8) | ((n - 1) << 4) | msg.prefix[-1]
        return _config_id(_OP_ACK, arg), value.to_bytes(8, "big")
    if isinstance(msg, Assign):
        return _config_id(_OP_ASSIGN, msg.txnode), msg.node_id.to_bytes(8, "big")
    if isinstance(msg, Reset):
        return _config_id(_OP_STATUS, (_ST_RESET << 8) | msg.epoch), b""
    if isinstance(msg, Hello):
        return _config_id(_OP_STATUS, (_ST_HELLO << 8) | msg.epoch), b""
    if isinstance(msg, TxNodesFull):
        return _config_id(_OP_STATUS, _ST_TXNODES_FULL << 8), msg.node_id.to_bytes(8, "big")
    if isinstance(msg, EtagsFull):
        return _config_id(_OP_STATUS, _ST_ETAGS_FULL << 8), msg.uid.to_bytes(8, "big")
    if isinstance(msg, Grant):
        data = struct.pack(">HBB4x", msg.etag, msg.txnode, msg.priority)
        return _config_id(_OP_STATUS, _ST_GRANT << 8), data
    if isinstance(msg, Refuse):
        data = struct.pack(
            ">HBBHH", msg.etag, msg.txnode, msg.miss_txnode, msg.miss_etag, msg.response_10us
        )
        return _config_id(_OP_STATUS, _ST_REFUSE << 8), data
    if isinstance(msg, Bind):
        return make_id(BIND_PRIORITY, MGMT_TXNODE, msg.etag), msg.uid.to_bytes(8, "big")
    if isinstance(msg, Declare):
        data = struct.pack(">HBHHB", msg.etag, msg.size_bytes, msg.period, msg.deadline, msg.jitter)
        return make_id(CONFIG_PRIORITY, msg.txnode, DECLARE), data
    return make_id(CONFIG_PRIORITY, msg.txnode, msg.kind), msg.value.to_bytes(8, "big")


def _config_id(op: int, arg: int) -> int:
    return make_id(CONFIG_PRIORITY, MGMT_TXNODE, (op << 12) | arg)


def decode(can_id: int, data: bytes) -> Management:
    """Decode a management frame (``is_management(can_id)`` must hold).

    Raises ``DecodeError`` when the frame is in the management space but malformed.
    """
    priority, txnode, etag = split_id(can_id)
    if txnode != MGMT_TXNODE:
        if priority == CONFIG_PRIORITY and etag == DECLARE:
            return _decode_declare(txnode, data, can_id)
        if priority != CONFIG_PRIORITY or etag not in _REQUEST_KINDS:
            raise DecodeError(f"unknown node request {can_id:#010x}")
        return Request(etag, txnode, _u64(data, can_id))
    if priority == BIND_PRIORITY:
        if etag < FIRST_ETAG:
            raise DecodeError(f"binding announcement for reserved etag {etag:#x}")
        return Bind(etag, _u64(data, can_id))
    if priority != CONFIG_PRIORITY:
        raise DecodeError(f"management frame with unknown priority {priority:#x}")
    op, arg = etag >> 12, etag & 0xFFF
    epoch, stage, nibble = arg >> 8, (arg >> 4) & 0xF, arg & 0xF
    if op == _OP_STAGE:
        _expect_len(data, 0, can_id)
        return Stage(epoch, stage, nibble)
    if op == _OP_ACK:
        value = _u64(data, can_id)
        prefix = nibbles_of(value)[: stage + 1]
        if prefix[-1] != nibble or value & ((1 << (4 * (NIBBLES - stage - 1))) - 1):
            raise DecodeError(f"inconsistent race state {can_id:#010x} {data.hex()}")
        return Ack(epoch, prefix)
    if op == _OP_ASSIGN:
        if arg >= TXNODE_COUNT:
            raise DecodeError(f"assignment of reserved TxNode {arg:#x}")
        return Assign(arg, _u64(data, can_id))
    status = arg >> 8
    if status in (_ST_RESET, _ST_HELLO) and arg & 0xF0 == 0:
        _expect_len(data, 0, can_id)
        return Reset(arg & 0xF) if status == _ST_RESET else Hello(arg & 0xF)
    if status == _ST_TXNODES_FULL and arg & 0xFF == 0:
        return TxNodesFull(_u64(data, can_id))
    if status == _ST_ETAGS_FULL and arg & 0xFF == 0:
        return EtagsFull(_u64(data, can_id))
    if status == _ST_GRANT and arg & 0xFF == 0:
        _expect_len(data, 8, can_id)
        etag, node, prio, pad = struct.unpack(">HBBI", data)
        if pad or not _stream_ok(etag, node):
            raise DecodeError(f"bad grant {data.hex()}")
        return Grant(etag, node, prio)
    if status == _ST_REFUSE and arg & 0xFF == 0:
        _expect_len(data, 8, can_id)
        etag, node, miss_node, miss_etag, response = struct.unpack(">HBBHH", data)
        if not (_stream_ok(etag, node) and _stream_ok(miss_etag, miss_node)):
            raise DecodeError(f"bad refusal {data.hex()}")
        return Refuse(etag, node, miss_etag, miss_node, response)
    raise DecodeError(f"unknown status frame {can_id:#010x}")


def _stream_ok(etag: int, txnode: int) -> bool:
    return FIRST_ETAG <= etag <= LAST_ETAG and txnode < TXNODE_COUNT


def _decode_declare(txnode: int, data: bytes, can_id: int) -> Declare:
    _expect_len(data, 8, can_id)
    etag, size, period, deadline, jitter = struct.unpack(">HBHHB", data)
    if not (FIRST_ETAG <= etag <= LAST_ETAG and size <= CLASSIC_MAX_DATA and period and deadline):
        raise DecodeError(f"bad declaration {data.hex()}")
    return Declare(txnode, etag, size, period, deadline, jitter)


def _expect_len(data: bytes, n: int, can_id: int) -> None:
    if len(data) != n:
        raise DecodeError(f"frame {can_id:#010x} must carry {n} bytes, got {len(data)}")


def _u64(data: bytes, can_id: int) -> int:
    _expect_len(data, 8, can_id)
    return int.from_bytes(data, "big")
