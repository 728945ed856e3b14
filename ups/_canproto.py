"""UPS on CAN: the management frames, as records and a pure codec (``encode``/``decode``).

No I/O here. ``docs/protocol.md`` describes the same frames byte by byte; keep them in step.
The 29-bit identifier they are laid out in (``make_id``, ``split_id``, ``is_management``, its
fields and reserved values) is ``_canid``'s, and is imported from here too, by the users of
both.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from ._canid import BIND_PRIORITY as BIND_PRIORITY
from ._canid import CLASSIC_MAX_DATA as CLASSIC_MAX_DATA
from ._canid import CONFIG_PRIORITY as CONFIG_PRIORITY
from ._canid import ETAG_MASK as ETAG_MASK
from ._canid import FIRST_ETAG as FIRST_ETAG
from ._canid import FIRST_EVENT_PRIORITY as FIRST_EVENT_PRIORITY
from ._canid import LARGE_FIRST_ETAG as LARGE_FIRST_ETAG
from ._canid import LAST_ETAG as LAST_ETAG
from ._canid import MGMT_TXNODE as MGMT_TXNODE
from ._canid import NIBBLES as NIBBLES
from ._canid import PRIORITY_MASK as PRIORITY_MASK
from ._canid import PRIORITY_SHIFT as PRIORITY_SHIFT
from ._canid import TXNODE_COUNT as TXNODE_COUNT
from ._canid import TXNODE_MASK as TXNODE_MASK
from ._canid import TXNODE_SHIFT as TXNODE_SHIFT
from ._canid import id_of as id_of
from ._canid import is_management as is_management
from ._canid import make_id as make_id
from ._canid import nibbles_of as nibbles_of
from ._canid import split_id as split_id
from ._errors import DecodeError
from ._face import DEFAULT_PRIORITY as DEFAULT_PRIORITY  # events, unless the channel's is set

EPOCHS = 16  #: a query's epoch fits 4 bits: 0..15


# --- configuration (priority 0x00, TxNode 0x7F, etag field = op (2 bits) | arg (12 bits)) ----

_OP_STAGE, _OP_QUERY, _OP_ASSIGN, _OP_STATUS = 0, 1, 2, 3
_ST_CENSUS, _ST_TXNODES_FULL, _ST_ETAGS_FULL, _ST_HELLO, _ST_GRANT, _ST_REFUSE = range(6)
_ST_SERVING, _ST_FAILED, _ST_LIMIT, _ST_PROBE = 6, 7, 8, 9
_ST_USES_SUB, _ST_USES_PUB, _ST_ROSTER_END = 10, 11, 12
_ST_KNOCK = 0xF
_OFFER = 0x80  #: in an Assign frame's argument: only an offer


@dataclass(frozen=True, slots=True)
class Knock:
    """A node without a TxNode asks the CAN-ECB for a census (every joiner sends the same)."""


@dataclass(frozen=True, slots=True)
class Census:
    """The CAN-ECB asks every node without a TxNode for its id: query ``epoch``, empty prefix."""

    epoch: int


@dataclass(frozen=True, slots=True)
class Query:
    """The CAN-ECB asks the joiners whose id starts with ``prefix`` (1..15 nibbles) for the
    rest of it, in query ``epoch``."""

    epoch: int
    prefix: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class Stage:
    """A joiner's answer to query ``epoch``: nibble ``stage`` of its id is ``nibble``."""

    epoch: int
    stage: int
    nibble: int


@dataclass(frozen=True, slots=True)
class Offer:
    """The CAN-ECB found ``node_id`` in a census and offers it ``txnode``: the node claims it
    (CLAIM from ``txnode``) before it is assigned, so no TxNode goes to an id nobody has."""

    txnode: int
    node_id: int


@dataclass(frozen=True, slots=True)
class Assign:
    """The CAN-ECB gives ``txnode`` to the node whose 64-bit id is ``node_id``."""

    txnode: int
    node_id: int


@dataclass(frozen=True, slots=True)
class Hello:
    """CAN-ECB ``instance`` has just started (or lost track of the bus): configured nodes
    announce their TxNode and channels again."""

    instance: int


@dataclass(frozen=True, slots=True)
class Serving:
    """CAN-ECB ``instance`` serves this bus (the answer to another CAN-ECB's frames)."""

    instance: int


@dataclass(frozen=True, slots=True)
class Probe:
    """CAN-ECB ``instance`` stands by and asks whether another serves (a serving CAN-ECB answers
    with its Serving; a Probe never makes one stand by)."""

    instance: int


@dataclass(frozen=True, slots=True)
class TxNodesFull:
    """No TxNode is left for ``node_id``."""

    node_id: int


@dataclass(frozen=True, slots=True)
class EtagsFull:
    """No etag is left for channel ``uid``."""

    uid: int


@dataclass(frozen=True, slots=True)
class Failed:
    """The CAN-ECB could not store the assignment or binding of ``value`` (a node id or a
    channel UID): its storage fails. Ask again later."""

    value: int


@dataclass(frozen=True, slots=True)
class Limit:
    """``txnode`` already uses as many channels as the CAN-ECB allows one node; ``uid`` is
    refused."""

    txnode: int
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


@dataclass(frozen=True, slots=True)
class Uses:
    """Part of the CAN-ECB's answer to a Roster: node ``txnode`` subscribes to (``publish``
    false) or publishes on (true) channel ``uid``."""

    publish: bool
    txnode: int
    uid: int


@dataclass(frozen=True, slots=True)
class RosterEnd:
    """The end of one answer to the Roster of ``txnode``: ``done``, the roster is complete
    (``next`` is 0); else ask again from ``next`` (the lowest UID not listed yet)."""

    txnode: int
    next: int
    done: bool


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
CLAIM = 0x0004  #: "I hold this TxNode": the answer to Hello
DECLARE = 0x0005  #: a real-time declaration (see Declare)
ROSTER = 0x0006  #: who uses which channel, from a UID on (see Roster)
PUB_BIND_CLASS = 0x0008  #: 0x0009..0x000C: PUB_BIND for events of size class 1..4
SIZE_CLASSES = 5  #: size class 0 (one frame) and the four classes of larger events
_REQUEST_KINDS = (PUB_BIND, SUB_BIND, UNSUB, CLAIM)


@dataclass(frozen=True, slots=True)
class Request:
    """A configured node's request; ``value`` is a channel UID, or the node id for CLAIM.
    A PUB_BIND asks for an etag of at least ``size_class`` (see ``_cantransfer``)."""

    kind: int
    txnode: int
    value: int
    size_class: int = 0


@dataclass(frozen=True, slots=True)
class Holds:
    """``txnode`` uses channel ``uid`` at ``etag``: it subscribes to it (SUB_AT, priority 0x00)
    or publishes on it (PUB_AT, priority 0x01)."""

    publish: bool
    txnode: int
    etag: int
    uid: int


@dataclass(frozen=True, slots=True)
class Declare:
    """``txnode`` publishes on ``etag`` at most one event every ``period``, released up to
    ``jitter`` late, due within ``deadline``; all in units of 100 us. ``size_bytes`` is the
    event's size on a one-frame etag (0..8), its number of frames on a larger one (1..255)."""

    txnode: int
    etag: int
    size_bytes: int
    period: int  # 1..65535
    deadline: int  # 1..65535
    jitter: int  # 0..255


@dataclass(frozen=True, slots=True)
class Roster:
    """A joined node asks the CAN-ECB who uses the channels whose UIDs are ``cursor`` or
    higher (a gateway that joins a running bus); answered with Uses frames, then RosterEnd."""

    txnode: int
    cursor: int


Management = (
    Knock
    | Census
    | Query
    | Stage
    | Offer
    | Assign
    | Hello
    | Serving
    | Probe
    | TxNodesFull
    | EtagsFull
    | Failed
    | Limit
    | Grant
    | Refuse
    | Bind
    | Request
    | Holds
    | Declare
    | Roster
    | Uses
    | RosterEnd
)

#: The frames only a CAN-ECB sends (a CAN-ECB that hears one it did not send knows that
#: another CAN-ECB, or a forger, is on the bus).
ECB_FRAMES = (
    Census, Query, Offer, Assign, Hello, Serving, Probe, TxNodesFull, EtagsFull, Failed, Limit,
    Grant, Refuse, Bind, Uses, RosterEnd,
)  # fmt: skip


def encode(msg: Management) -> tuple[int, bytes]:
    """The ``(arbitration_id, data)`` of a management frame."""
    if isinstance(msg, Stage):
        arg = (msg.epoch << 8) | (msg.stage << 4) | msg.nibble
        return _config_id(_OP_STAGE, arg), b""
    if isinstance(msg, Query):
        n = len(msg.prefix)
        value = id_of(msg.prefix) << (4 * (NIBBLES - n))
        arg = (msg.epoch << 8) | ((n - 1) << 4) | msg.prefix[-1]
        return _config_id(_OP_QUERY, arg), value.to_bytes(8, "big")
    if isinstance(msg, Assign):
        return _config_id(_OP_ASSIGN, msg.txnode), msg.node_id.to_bytes(8, "big")
    if isinstance(msg, Offer):
        return _config_id(_OP_ASSIGN, _OFFER | msg.txnode), msg.node_id.to_bytes(8, "big")
    if isinstance(msg, Census):
        return _config_id(_OP_STATUS, (_ST_CENSUS << 8) | msg.epoch), b""
    if isinstance(msg, Knock):
        return _config_id(_OP_STATUS, _ST_KNOCK << 8), b""
    if isinstance(msg, Hello):
        return _config_id(_OP_STATUS, _ST_HELLO << 8), msg.instance.to_bytes(8, "big")
    if isinstance(msg, Serving):
        return _config_id(_OP_STATUS, _ST_SERVING << 8), msg.instance.to_bytes(8, "big")
    if isinstance(msg, Probe):
        return _config_id(_OP_STATUS, _ST_PROBE << 8), msg.instance.to_bytes(8, "big")
    if isinstance(msg, TxNodesFull):
        return _config_id(_OP_STATUS, _ST_TXNODES_FULL << 8), msg.node_id.to_bytes(8, "big")
    if isinstance(msg, EtagsFull):
        return _config_id(_OP_STATUS, _ST_ETAGS_FULL << 8), msg.uid.to_bytes(8, "big")
    if isinstance(msg, Failed):
        return _config_id(_OP_STATUS, _ST_FAILED << 8), msg.value.to_bytes(8, "big")
    if isinstance(msg, Limit):
        return _config_id(_OP_STATUS, (_ST_LIMIT << 8) | msg.txnode), msg.uid.to_bytes(8, "big")
    if isinstance(msg, Grant):
        data = struct.pack(">HBB4x", msg.etag, msg.txnode, msg.priority)
        return _config_id(_OP_STATUS, _ST_GRANT << 8), data
    if isinstance(msg, Refuse):
        data = struct.pack(
            ">HBBHH", msg.etag, msg.txnode, msg.miss_txnode, msg.miss_etag, msg.response_10us
        )
        return _config_id(_OP_STATUS, _ST_REFUSE << 8), data
    if isinstance(msg, Uses):
        status = _ST_USES_PUB if msg.publish else _ST_USES_SUB
        return _config_id(_OP_STATUS, (status << 8) | msg.txnode), msg.uid.to_bytes(8, "big")
    if isinstance(msg, RosterEnd):
        arg = (_ST_ROSTER_END << 8) | (0x80 if msg.done else 0) | msg.txnode
        return _config_id(_OP_STATUS, arg), msg.next.to_bytes(8, "big")
    if isinstance(msg, Roster):
        return make_id(CONFIG_PRIORITY, msg.txnode, ROSTER), msg.cursor.to_bytes(8, "big")
    if isinstance(msg, Bind):
        return make_id(BIND_PRIORITY, MGMT_TXNODE, msg.etag), msg.uid.to_bytes(8, "big")
    if isinstance(msg, Holds):
        priority = BIND_PRIORITY if msg.publish else CONFIG_PRIORITY
        return make_id(priority, msg.txnode, msg.etag), msg.uid.to_bytes(8, "big")
    if isinstance(msg, Declare):
        data = struct.pack(">HBHHB", msg.etag, msg.size_bytes, msg.period, msg.deadline, msg.jitter)
        return make_id(CONFIG_PRIORITY, msg.txnode, DECLARE), data
    kind = PUB_BIND_CLASS | msg.size_class if msg.size_class else msg.kind
    return make_id(CONFIG_PRIORITY, msg.txnode, kind), msg.value.to_bytes(8, "big")


def _config_id(op: int, arg: int) -> int:
    return make_id(CONFIG_PRIORITY, MGMT_TXNODE, (op << 12) | arg)


def decode(can_id: int, data: bytes) -> Management:
    """Decode a management frame (``is_management(can_id)`` must hold).

    Raises ``DecodeError`` when the frame is in the management space but malformed.
    """
    priority, txnode, etag = split_id(can_id)
    if txnode != MGMT_TXNODE:
        return _decode_node_frame(priority, txnode, etag, data, can_id)
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
    if op == _OP_QUERY:
        value = _u64(data, can_id)
        prefix = nibbles_of(value)[: stage + 1]
        if stage == NIBBLES - 1 or prefix[-1] != nibble:
            raise DecodeError(f"inconsistent query {can_id:#010x} {data.hex()}")
        if value & ((1 << (4 * (NIBBLES - stage - 1))) - 1):
            raise DecodeError(f"inconsistent query {can_id:#010x} {data.hex()}")
        return Query(epoch, prefix)
    if op == _OP_ASSIGN:
        if arg & ~_OFFER >= TXNODE_COUNT:
            raise DecodeError(f"assignment of reserved TxNode {arg:#x}")
        if arg & _OFFER:
            return Offer(arg & ~_OFFER, _u64(data, can_id))
        return Assign(arg, _u64(data, can_id))
    return _decode_status(arg >> 8, arg & 0xFF, data, can_id)


def _decode_status(status: int, low: int, data: bytes, can_id: int) -> Management:
    if status == _ST_CENSUS and low < EPOCHS:
        _expect_len(data, 0, can_id)
        return Census(low)
    if status == _ST_LIMIT and low < TXNODE_COUNT:
        return Limit(low, _u64(data, can_id))
    if status in (_ST_USES_SUB, _ST_USES_PUB) and low < TXNODE_COUNT:
        return Uses(status == _ST_USES_PUB, low, _u64(data, can_id))
    if status == _ST_ROSTER_END and low & 0x7F < TXNODE_COUNT:
        value, done = _u64(data, can_id), bool(low & 0x80)
        if done and value:
            raise DecodeError(f"a complete roster names no next UID: {can_id:#010x}")
        return RosterEnd(low & 0x7F, value, done)
    if low:
        raise DecodeError(f"unknown status frame {can_id:#010x}")
    if status == _ST_KNOCK:
        _expect_len(data, 0, can_id)
        return Knock()
    if status == _ST_HELLO:
        return Hello(_u64(data, can_id))
    if status == _ST_SERVING:
        return Serving(_u64(data, can_id))
    if status == _ST_PROBE:
        return Probe(_u64(data, can_id))
    if status == _ST_TXNODES_FULL:
        return TxNodesFull(_u64(data, can_id))
    if status == _ST_ETAGS_FULL:
        return EtagsFull(_u64(data, can_id))
    if status == _ST_FAILED:
        return Failed(_u64(data, can_id))
    if status == _ST_GRANT:
        _expect_len(data, 8, can_id)
        etag, node, prio, pad = struct.unpack(">HBBI", data)
        if pad or not _stream_ok(etag, node):
            raise DecodeError(f"bad grant {data.hex()}")
        return Grant(etag, node, prio)
    if status == _ST_REFUSE:
        _expect_len(data, 8, can_id)
        etag, node, miss_node, miss_etag, response = struct.unpack(">HBBHH", data)
        if not (_stream_ok(etag, node) and _stream_ok(miss_etag, miss_node)):
            raise DecodeError(f"bad refusal {data.hex()}")
        return Refuse(etag, node, miss_etag, miss_node, response)
    raise DecodeError(f"unknown status frame {can_id:#010x}")


def _decode_node_frame(
    priority: int, txnode: int, etag: int, data: bytes, can_id: int
) -> Management:
    if etag >= FIRST_ETAG:  # SUB_AT (0x00) or PUB_AT (0x01); events never get here
        if priority > BIND_PRIORITY:
            raise DecodeError(f"not a management frame {can_id:#010x}")
        return Holds(priority == BIND_PRIORITY, txnode, etag, _u64(data, can_id))
    if priority == CONFIG_PRIORITY and etag == DECLARE:
        _expect_len(data, 8, can_id)
        etag, size, period, deadline, jitter = struct.unpack(">HBHHB", data)
        largest = CLASSIC_MAX_DATA if etag < LARGE_FIRST_ETAG else 0xFF
        if not (
            FIRST_ETAG <= etag <= LAST_ETAG
            and size <= largest
            and (size or etag < LARGE_FIRST_ETAG)
            and period
            and deadline
        ):
            raise DecodeError(f"bad declaration {data.hex()}")
        return Declare(txnode, etag, size, period, deadline, jitter)
    if priority == CONFIG_PRIORITY and etag == ROSTER:
        return Roster(txnode, _u64(data, can_id))
    if priority == CONFIG_PRIORITY and PUB_BIND_CLASS < etag < PUB_BIND_CLASS + SIZE_CLASSES:
        return Request(PUB_BIND, txnode, _u64(data, can_id), etag - PUB_BIND_CLASS)
    if priority != CONFIG_PRIORITY or etag not in _REQUEST_KINDS:
        raise DecodeError(f"unknown node request {can_id:#010x}")
    return Request(etag, txnode, _u64(data, can_id))


def _stream_ok(etag: int, txnode: int) -> bool:
    return FIRST_ETAG <= etag <= LAST_ETAG and txnode < TXNODE_COUNT


def _expect_len(data: bytes, n: int, can_id: int) -> None:
    if len(data) != n:
        raise DecodeError(f"frame {can_id:#010x} must carry {n} bytes, got {len(data)}")


def _u64(data: bytes, can_id: int) -> int:
    _expect_len(data, 8, can_id)
    return int.from_bytes(data, "big")
