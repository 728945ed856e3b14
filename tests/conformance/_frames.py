"""UPS CAN frames, built and parsed from docs/protocol.md alone (section "CAN").

Nothing here comes from the implementation: every constant is read off the document's tables
(identifier layout, priority bands, management frames, real-time data layouts).
"""

from __future__ import annotations

from dataclasses import dataclass

import can

# --- identifier layout: priority 8 | TxNode 7 | etag 14 -------------------------------------
ECB = 0x7F  #: the CAN-ECB's TxNode, and that of joining nodes
MAX_TXNODE = 0x7E  #: the CAN-ECB gives out TxNodes 0x00-0x7E
FIRST_ETAG = 0x0010  #: the CAN-ECB binds etags 0x0010-0x3FFF
LAST_ETAG = 0x3FFF
BEST_EFFORT = 0x80  #: default priority of best-effort events

# --- node requests: priority 0x00, own TxNode, etag 0x0001-0x0005, 8 data bytes -------------
PUB_BIND, SUB_BIND, UNSUB, CLAIM, DECLARE, ROSTER = 1, 2, 3, 4, 5, 6
REQUEST_NAMES = {PUB_BIND: "PUB_BIND", SUB_BIND: "SUB_BIND", UNSUB: "UNSUB", CLAIM: "CLAIM"}

# --- CAN-ECB / joiner frames: priority 0x00, TxNode 0x7F, op in the etag's two high bits -----
OP_STAGE, OP_QUERY, OP_ASSIGN, OP_STATUS = 0b00, 0b01, 0b10, 0b11
OFFER_BIT = 0x80  #: in the etag field of op 0b10: an Offer, not an Assign
# status codes: bits 11..8 of the etag field when the op is 0b11
S_CENSUS, S_TXNODES_FULL, S_ETAGS_FULL, S_HELLO, S_GRANT = 0x0, 0x1, 0x2, 0x3, 0x4
S_REFUSE, S_SERVING, S_FAILED, S_LIMIT, S_PROBE, S_KNOCK = 0x5, 0x6, 0x7, 0x8, 0x9, 0xF
S_USES_SUB, S_USES_PUB, S_ROSTER_END = 0xA, 0xB, 0xC
DONE_BIT = 0x80  #: in RosterEnd's etag field: the roster is complete


def ident(priority: int, txnode: int, etag: int) -> int:
    """``priority << 21 | txnode << 14 | etag``."""
    assert 0 <= priority <= 0xFF and 0 <= txnode <= 0x7F and 0 <= etag <= 0x3FFF
    return priority << 21 | txnode << 14 | etag


def fields(identifier: int) -> tuple[int, int, int]:
    """(priority, TxNode, etag) of a 29-bit identifier."""
    return identifier >> 21 & 0xFF, identifier >> 14 & 0x7F, identifier & 0x3FFF


def _status(code: int, low: int = 0) -> int:
    return ident(0, ECB, OP_STATUS << 12 | code << 8 | low)


def _u64(value: int) -> bytes:
    return value.to_bytes(8, "big")


# --- the frames, as values (frozen dataclasses: two frames are equal only if of one kind) ----


@dataclass(frozen=True, order=True)
class Stage:
    epoch: int
    stage: int
    nibble: int


@dataclass(frozen=True, order=True)
class Query:
    epoch: int
    prefix: tuple[int, ...]


@dataclass(frozen=True, order=True)
class Offer:
    txnode: int
    node_id: int


@dataclass(frozen=True, order=True)
class Assign:
    txnode: int
    node_id: int


@dataclass(frozen=True, order=True)
class Census:
    epoch: int


@dataclass(frozen=True, order=True)
class TxNodesFull:
    node_id: int


@dataclass(frozen=True, order=True)
class EtagsFull:
    uid: int


@dataclass(frozen=True, order=True)
class Hello:
    instance: int


@dataclass(frozen=True, order=True)
class Grant:
    etag: int
    txnode: int
    priority: int


@dataclass(frozen=True, order=True)
class Refuse:
    etag: int
    txnode: int
    miss_txnode: int
    miss_etag: int
    response_10us: int


@dataclass(frozen=True, order=True)
class Serving:
    instance: int


@dataclass(frozen=True, order=True)
class Probe:
    instance: int


@dataclass(frozen=True, order=True)
class Failed:
    value: int


@dataclass(frozen=True, order=True)
class Limit:
    txnode: int
    uid: int


@dataclass(frozen=True, order=True)
class Knock:
    pass


@dataclass(frozen=True, order=True)
class Uses:
    publish: bool
    txnode: int
    uid: int


@dataclass(frozen=True, order=True)
class RosterEnd:
    txnode: int  #: the node whose Roster this answers
    next: int
    done: bool


@dataclass(frozen=True, order=True)
class Roster:
    txnode: int
    cursor: int


@dataclass(frozen=True, order=True)
class Bind:
    etag: int
    uid: int


@dataclass(frozen=True, order=True)
class Request:
    """PUB_BIND, SUB_BIND, UNSUB or CLAIM (``kind`` is the etag 1-4)."""

    kind: int
    txnode: int
    value: int


@dataclass(frozen=True, order=True)
class Declare:
    txnode: int
    etag: int
    size: int
    period: int  #: 100 us
    deadline: int  #: 100 us
    jitter: int  #: 100 us


@dataclass(frozen=True, order=True)
class SubAt:
    txnode: int
    etag: int
    uid: int


@dataclass(frozen=True, order=True)
class PubAt:
    txnode: int
    etag: int
    uid: int


@dataclass(frozen=True, order=True)
class Event:
    priority: int
    txnode: int
    etag: int
    data: bytes


@dataclass(frozen=True, order=True)
class Malformed:
    identifier: int
    data: bytes


@dataclass(frozen=True, order=True)
class Foreign:
    why: str


Frame = (
    Stage
    | Query
    | Offer
    | Assign
    | Census
    | TxNodesFull
    | EtagsFull
    | Hello
    | Grant
    | Refuse
    | Serving
    | Probe
    | Failed
    | Limit
    | Knock
    | Uses
    | RosterEnd
    | Roster
    | Bind
    | Request
    | Declare
    | SubAt
    | PubAt
    | Event
    | Malformed
    | Foreign
)

#: frames that only a CAN-ECB sends
ECB_FRAMES = (
    Census,
    Query,
    Offer,
    Assign,
    Hello,
    Serving,
    Probe,
    TxNodesFull,
    EtagsFull,
    Failed,
    Limit,
    Grant,
    Refuse,
    Bind,
    Uses,
    RosterEnd,
)


def sub_bind(txnode: int, uid: int) -> Request:
    return Request(SUB_BIND, txnode, uid)


def pub_bind(txnode: int, uid: int) -> Request:
    return Request(PUB_BIND, txnode, uid)


def unsub(txnode: int, uid: int) -> Request:
    return Request(UNSUB, txnode, uid)


def claim(txnode: int, node_id: int) -> Request:
    return Request(CLAIM, txnode, node_id)


def nibbles(value: int, count: int = 16) -> tuple[int, ...]:
    """The first ``count`` nibbles of a 64-bit value, most significant first."""
    return tuple(value >> (60 - 4 * i) & 0xF for i in range(count))


# --- encoding -------------------------------------------------------------------------------


def encode(frame: Frame) -> tuple[int, bytes]:
    """The 29-bit identifier and the data of ``frame``, as the document's tables lay them out."""
    match frame:
        case Stage(e, s, n):
            return ident(0, ECB, OP_STAGE << 12 | e << 8 | s << 4 | n), b""
        case Query(e, prefix):
            assert 1 <= len(prefix) <= 15
            value = 0
            for i, nib in enumerate(prefix):
                value |= nib << (60 - 4 * i)
            etag = OP_QUERY << 12 | e << 8 | (len(prefix) - 1) << 4 | prefix[-1]
            return ident(0, ECB, etag), _u64(value)
        case Offer(t, node_id):
            return ident(0, ECB, OP_ASSIGN << 12 | OFFER_BIT | t), _u64(node_id)
        case Assign(t, node_id):
            return ident(0, ECB, OP_ASSIGN << 12 | t), _u64(node_id)
        case Census(e):
            return _status(S_CENSUS, e), b""
        case TxNodesFull(v):
            return _status(S_TXNODES_FULL), _u64(v)
        case EtagsFull(v):
            return _status(S_ETAGS_FULL), _u64(v)
        case Hello(v):
            return _status(S_HELLO), _u64(v)
        case Grant(etag, t, prio):
            return _status(S_GRANT), etag.to_bytes(2, "big") + bytes([t, prio, 0, 0, 0, 0])
        case Refuse(etag, t, mt, me, resp):
            data = etag.to_bytes(2, "big") + bytes([t, mt]) + me.to_bytes(2, "big")
            return _status(S_REFUSE), data + resp.to_bytes(2, "big")
        case Serving(v):
            return _status(S_SERVING), _u64(v)
        case Probe(v):
            return _status(S_PROBE), _u64(v)
        case Failed(v):
            return _status(S_FAILED), _u64(v)
        case Limit(t, uid):
            return _status(S_LIMIT, t), _u64(uid)
        case Knock():
            return _status(S_KNOCK), b""
        case Uses(publish, t, uid):
            return _status(S_USES_PUB if publish else S_USES_SUB, t), _u64(uid)
        case RosterEnd(t, after, done):
            return _status(S_ROSTER_END, (DONE_BIT if done else 0) | t), _u64(after)
        case Roster(t, cursor):
            return ident(0, t, ROSTER), _u64(cursor)
        case Bind(etag, uid):
            return ident(1, ECB, etag), _u64(uid)
        case Request(kind, t, value):
            return ident(0, t, kind), _u64(value)
        case Declare(t, etag, size, period, deadline, jitter):
            data = (
                etag.to_bytes(2, "big")
                + bytes([size])
                + period.to_bytes(2, "big")
                + deadline.to_bytes(2, "big")
                + bytes([jitter])
            )
            return ident(0, t, DECLARE), data
        case SubAt(t, etag, uid):
            return ident(0, t, etag), _u64(uid)
        case PubAt(t, etag, uid):
            return ident(1, t, etag), _u64(uid)
        case Event(prio, t, etag, data):
            return ident(prio, t, etag), bytes(data)
        case Malformed(identifier, data):
            return identifier, bytes(data)
    raise TypeError(f"cannot encode {frame!r}")


def message(frame: Frame) -> can.Message:
    """``frame`` as a python-can 29-bit data frame."""
    identifier, data = encode(frame)
    return can.Message(arbitration_id=identifier, data=data, is_extended_id=True)


# --- decoding -------------------------------------------------------------------------------


def decode(msg: can.Message) -> Frame:
    """What a participant following the document makes of ``msg``."""
    if not msg.is_extended_id:
        return Foreign("11-bit identifier")
    if msg.is_remote_frame:
        return Foreign("remote frame")
    if msg.is_error_frame:
        return Foreign("error frame")
    if msg.is_fd:
        return Foreign("CAN FD frame")
    return decode_id(msg.arbitration_id, bytes(msg.data))


def decode_id(identifier: int, data: bytes) -> Frame:
    """Decode a 29-bit data frame (identifier and data)."""
    prio, tx, etag = fields(identifier)
    if prio > 0x01 and tx != ECB and etag >= FIRST_ETAG:
        return Event(prio, tx, etag, data)
    bad = Malformed(identifier, data)
    value = int.from_bytes(data, "big") if len(data) == 8 else None
    if tx == ECB:
        if prio == 0x00:
            frame = _decode_ecb(etag, data)  # (Knock() is an empty tuple: test against None)
            return bad if frame is None else frame
        if prio == 0x01 and etag >= FIRST_ETAG and value is not None:
            return Bind(etag, value)
        return bad
    if prio == 0x00 and PUB_BIND <= etag <= CLAIM and value is not None:
        return Request(etag, tx, value)
    if prio == 0x00 and etag == ROSTER and value is not None:
        return Roster(tx, value)
    if prio == 0x00 and etag == DECLARE and len(data) == 8:
        return Declare(
            tx,
            int.from_bytes(data[0:2], "big"),
            data[2],
            int.from_bytes(data[3:5], "big"),
            int.from_bytes(data[5:7], "big"),
            data[7],
        )
    if prio == 0x00 and etag >= FIRST_ETAG and value is not None:
        return SubAt(tx, etag, value)
    if prio == 0x01 and etag >= FIRST_ETAG and value is not None:
        return PubAt(tx, etag, value)
    return bad


def _decode_ecb(etag: int, data: bytes) -> Frame | None:
    """A CAN-ECB's or joiner's frame (priority 0x00, TxNode 0x7F), or None when malformed."""
    op, a, b, c = etag >> 12, etag >> 8 & 0xF, etag >> 4 & 0xF, etag & 0xF
    value = int.from_bytes(data, "big") if len(data) == 8 else None
    if op == OP_STAGE:
        return Stage(a, b, c) if not data else None
    if op == OP_QUERY:
        # l+1 nibbles, the last one n; 1 to 15 nibbles; nibbles past the prefix are zero
        if value is None or b + 1 > 15:
            return None
        prefix = nibbles(value, b + 1)
        if prefix[-1] != c or value & ((1 << (64 - 4 * (b + 1))) - 1):
            return None
        return Query(a, prefix)
    if op == OP_ASSIGN:  # Offer: 10 0000 1ttt tttt, Assign: 10 0000 0ttt tttt
        if etag & 0x0F00 or value is None:
            return None
        return (Offer if etag & OFFER_BIT else Assign)(etag & 0x7F, value)
    low = etag & 0xFF
    if a == S_CENSUS:
        return Census(c) if b == 0 and not data else None
    if a == S_KNOCK:
        return Knock() if low == 0 and not data else None
    if a == S_LIMIT:
        return Limit(low, value) if not low & 0x80 and value is not None else None
    if a in (S_USES_SUB, S_USES_PUB):  # 11 101p 0ttt tttt
        return Uses(a == S_USES_PUB, low, value) if low < 0x7F and value is not None else None
    if a == S_ROSTER_END:  # 11 1100 dttt tttt; done: the next UID is 0
        t, done = low & 0x7F, bool(low & DONE_BIT)
        if t == 0x7F or value is None or (done and value):
            return None
        return RosterEnd(t, value, done)
    if low or value is None:
        return None
    if a == S_GRANT:
        if data[4:] != bytes(4):
            return None
        return Grant(int.from_bytes(data[0:2], "big"), data[2], data[3])
    if a == S_REFUSE:
        return Refuse(
            int.from_bytes(data[0:2], "big"),
            data[2],
            data[3],
            int.from_bytes(data[4:6], "big"),
            int.from_bytes(data[6:8], "big"),
        )
    kinds = {
        S_TXNODES_FULL: TxNodesFull,
        S_ETAGS_FULL: EtagsFull,
        S_HELLO: Hello,
        S_SERVING: Serving,
        S_PROBE: Probe,
        S_FAILED: Failed,
    }
    cls = kinds.get(a)
    return cls(value) if cls is not None else None
