"""UPS on TCP/IP: one framing for every TCP link (node <-> ECB, node <-> node, gateway), pure.

A frame is a 4-byte header, ``version (u8) | body length (u24, big-endian)``, then the body.
An Event's body is binary and fixed: ``0x01 | priority (u8) | uid (u64) | seq (u64) | data``,
so the hot path decodes it with one ``struct`` call. Every other frame's body is a msgpack
array whose first element says what the frame is (an array never starts with the byte 0x01).
``docs/protocol.md`` has the table. Decoding bad bytes raises ``DecodeError``; whoever reads a
link closes that link and goes on.
"""

from __future__ import annotations

import mmap
import reprlib
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, TypeVar

import msgpack

from ._errors import DecodeError

VERSION: Final = 2
HEADER: Final = 4
EVENT_HEADER: Final = 22  #: header, kind, priority, uid and seq: what precedes an event's data
MAX_BODY: Final = (1 << 24) - 1
MAX_DATA = 1 << 20  #: the most data an event carries (1 MiB) ...
DEFAULT_MAX_FRAME = MAX_DATA + 18  #: ... in the longest body a receiver accepts by default

(
    _HELLO, _EVENT, _SUB, _UNSUB, _ADVERTISE, _UNADVERTISE, _SUBSCRIBERS, _PING, _PONG,
    _STATUS_REQUEST, _STATUS, _START, _PUBLISHERS, _REFUSED, _WATCH, _UNWATCH, _NAMES,
) = range(17)  # fmt: skip
NAMES_PER_FRAME: Final = 256  #: channels one Names frame lists at most
_HEAD = struct.Struct(">I")
_EVENT_HEAD = struct.Struct(">IBBQQ")  # header, kind (_EVENT), priority, uid, seq
#: a whole Event frame, by its data size up to 256 bytes: header, kind, priority, uid, seq, data
_WHOLE = tuple(struct.Struct(f">IBBQQ{size}s") for size in range(257))
_pack_event = _EVENT_HEAD.pack
_T = TypeVar("_T")
_STATUS_READERS: Final = 17  # (14, 15 and 16 are taken: Watch, Unwatch, Names)


@dataclass(frozen=True, slots=True)
class Hello:
    """First frame on every link: who is speaking, and where it listens for its peers."""

    node_id: int
    name: str
    host: str
    port: int


@dataclass(frozen=True, slots=True)
class Event:
    """``seq`` numbers the events of one publisher on one channel, 1, 2, 3, ... for all its
    subscribers alike: a subscriber that sees a number skipped knows it lost events."""

    uid: int
    data: bytes
    priority: int
    seq: int


@dataclass(frozen=True, slots=True)
class Start:
    """Publisher -> subscriber: your events of ``uid`` start at ``seq`` (sent when the
    subscriber becomes one of the channel's targets, before its first event)."""

    uid: int
    seq: int


@dataclass(frozen=True, slots=True)
class Subscribe:
    """The sender subscribes to ``uid``; ``name`` is the channel's name when the node knows it
    (the ECB checks that it hashes to ``uid``, and its access control list may match it)."""

    uid: int
    name: str | None = None


@dataclass(frozen=True, slots=True)
class Unsubscribe:
    uid: int


@dataclass(frozen=True, slots=True)
class Advertise:
    """The sender publishes on ``uid``: the ECB keeps it told of the channel's subscribers."""

    uid: int
    name: str | None = None


@dataclass(frozen=True, slots=True)
class Unadvertise:
    uid: int


@dataclass(frozen=True, slots=True)
class Peer:
    """A subscriber: where to reach it, and (with TLS) the identity its certificate must show."""

    node_id: int
    host: str
    port: int
    identity: str | None = None


@dataclass(frozen=True, slots=True)
class Publishers:
    """ECB -> subscriber: the nodes that publish on ``uid``, as (node id, identity) pairs (with
    TLS; empty without). A subscriber accepts events of ``uid`` only from a link whose Hello
    says one of these node ids and whose certificate shows that node's identity."""

    uid: int
    publishers: tuple[tuple[int, str], ...]


@dataclass(frozen=True, slots=True)
class StatusReaders:
    """ECB -> node (with TLS), after its Hello: the identities whose StatusRequests the node
    answers on its own links (the ACL's ``status`` right); None: every identity of the fleet
    (an ECB without an ACL). Until told, a node with TLS answers no one there."""

    identities: tuple[str, ...] | None


@dataclass(frozen=True, slots=True)
class Refused:
    """ECB -> node: ``right`` ("publish", "subscribe", "status" or "connect") on ``uid`` (0 for
    "status" and "connect") is not granted; ``reason`` says why, for people."""

    uid: int
    right: str
    reason: str


@dataclass(frozen=True, slots=True)
class Subscribers:
    """The ECB's complete, current list of the nodes subscribed to ``uid``."""

    uid: int
    peers: tuple[Peer, ...]


@dataclass(frozen=True, slots=True)
class Watch:
    """Node -> ECB: tell me the channels whose names match ``pattern`` (a glob), those known
    now (answered with Names, the last one ``done``) and those named later (pushed)."""

    pattern: str


@dataclass(frozen=True, slots=True)
class Unwatch:
    pattern: str


@dataclass(frozen=True, slots=True)
class Names:
    """ECB -> node: channels (UID, name) whose names match ``pattern``; ``done`` on the last
    frame of the answer to a Watch, and on every later push."""

    pattern: str
    channels: tuple[tuple[int, str], ...]
    done: bool = True


@dataclass(frozen=True, slots=True)
class Ping:
    pass


@dataclass(frozen=True, slots=True)
class Pong:
    pass


@dataclass(frozen=True, slots=True)
class StatusRequest:
    """Asks a daemon or node for its ``Status``; any link may carry it, before or after Hello."""


@dataclass(frozen=True, slots=True)
class Status:
    """A daemon's or node's counters and tables, as a msgpack map with string keys."""

    info: dict[str, Any]


RIGHTS = ("publish", "subscribe", "status", "connect", "watch")

Frame = (
    Hello
    | Event
    | Subscribe
    | Unsubscribe
    | Advertise
    | Unadvertise
    | Subscribers
    | Ping
    | Pong
    | StatusRequest
    | Status
    | StatusReaders
    | Start
    | Publishers
    | Refused
    | Watch
    | Unwatch
    | Names
)

_packer = msgpack.Packer(use_bin_type=True)


def encode(frame: Frame) -> bytes:
    """The bytes of one frame, header included."""
    if isinstance(frame, Event):
        return encode_event(frame.uid, frame.data, frame.priority, frame.seq)
    body: bytes = _packer.pack(_fields(frame))
    if len(body) > MAX_BODY:
        raise ValueError(f"frame body of {len(body)} bytes exceeds {MAX_BODY}")
    return (VERSION << 24 | len(body)).to_bytes(HEADER, "big") + body


def encode_event(uid: int, data: bytes, priority: int, seq: int) -> bytes:
    """The bytes of an Event frame: the publish hot path (no dataclass, no msgpack)."""
    size = len(data)
    if size > MAX_BODY - 18:
        raise ValueError(f"event of {size} bytes exceeds {MAX_BODY - 18}")
    return _pack_event(VERSION << 24 | (18 + size), _EVENT, priority, uid, seq) + data


def event_header(uid: int, size: int, priority: int, seq: int) -> bytes:
    """The ``EVENT_HEADER`` bytes that precede ``size`` bytes of data in an Event frame: a large
    event's data is written after them as it is, never copied into one buffer with them."""
    if size > MAX_BODY - 18:
        raise ValueError(f"event of {size} bytes exceeds {MAX_BODY - 18}")
    return _EVENT_HEAD.pack(VERSION << 24 | (18 + size), _EVENT, priority, uid, seq)


def _fields(frame: Frame) -> tuple[Any, ...]:
    if isinstance(frame, Start):
        return (_START, frame.uid, frame.seq)
    if isinstance(frame, Hello):
        return (_HELLO, frame.node_id, frame.name, frame.host, frame.port)
    if isinstance(frame, StatusReaders):
        readers = None if frame.identities is None else list(frame.identities)
        return (_STATUS_READERS, readers)
    if isinstance(frame, Subscribe):
        return (_SUB, frame.uid) if frame.name is None else (_SUB, frame.uid, frame.name)
    if isinstance(frame, Unsubscribe):
        return (_UNSUB, frame.uid)
    if isinstance(frame, Advertise):
        if frame.name is None:
            return (_ADVERTISE, frame.uid)
        return (_ADVERTISE, frame.uid, frame.name)
    if isinstance(frame, Unadvertise):
        return (_UNADVERTISE, frame.uid)
    if isinstance(frame, Subscribers):
        peers = [
            (p.node_id, p.host, p.port) if p.identity is None
            else (p.node_id, p.host, p.port, p.identity)
            for p in frame.peers
        ]  # fmt: skip
        return (_SUBSCRIBERS, frame.uid, peers)
    if isinstance(frame, Publishers):
        return (_PUBLISHERS, frame.uid, [list(p) for p in frame.publishers])
    if isinstance(frame, Refused):
        return (_REFUSED, frame.uid, frame.right, frame.reason)
    if isinstance(frame, Watch | Unwatch):
        return (_WATCH if isinstance(frame, Watch) else _UNWATCH, frame.pattern)
    if isinstance(frame, Names):
        return (_NAMES, frame.pattern, [list(c) for c in frame.channels], frame.done)
    if isinstance(frame, Status):
        return (_STATUS, frame.info)
    if isinstance(frame, StatusRequest):
        return (_STATUS_REQUEST,)
    return (_PING,) if isinstance(frame, Ping) else (_PONG,)


class Decoder:
    """Cuts a byte stream into frames. ``feed`` bytes as they come; it returns whole frames.

    Raises ``DecodeError`` on a wrong version, a frame longer than ``max_frame``, bytes that are
    not msgpack, or a body of the wrong shape; the stream is unusable after that.
    """

    def __init__(self, max_frame: int = DEFAULT_MAX_FRAME) -> None:
        self.max_frame = max_frame
        self._buf = bytearray()

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        buf = self._buf
        buf += data
        frames: list[Frame] = []
        pos = parse(buf, 0, len(buf), self.max_frame, frames, _append_event, list.append)
        if pos:
            del buf[:pos]
        return frames


def _append_event(frames: list[Frame], uid: int, data: bytes, priority: int, seq: int) -> None:
    frames.append(Event(uid, data, priority, seq))


def parse(
    buf: bytearray | mmap.mmap,
    pos: int,
    end: int,
    max_frame: int,
    owner: _T,
    on_event: Callable[[_T, int, bytes, int, int], None],
    on_frame: Callable[[_T, Frame], None],
    one_frame: bool = False,
) -> int:
    """Decode the whole frames in ``buf[pos:end]``; return where the first incomplete one starts.

    Events go to ``on_event(owner, uid, data, priority, seq)`` without building an ``Event``
    (the hot path), every other frame to ``on_frame(owner, frame)`` (``owner``: whatever the
    caller reads for, e.g. its link); with ``one_frame``, decoding stops after the first
    frame that is not an event (the caller may change ``max_frame`` in between). Raises
    ``DecodeError`` as ``Decoder.feed`` does; frames before the bad one have been handed over.
    """
    view = memoryview(buf)
    unpack_head, event = _HEAD.unpack_from, _EVENT  # locals: no lookup by name per frame
    # A stream's events are mostly of one size: the Struct of a whole Event frame of the last
    # size seen (data included, while small) decodes the next one in a single call. It reads
    # the fields at the same offsets whatever the size, so if the frame turns out to be of
    # another size only its data is read again.
    whole, body = _WHOLE[0].unpack_from, 18  # that Struct's unpack, and the body it covers
    kind = 0
    # Any, not int: the compiled build then passes the values unpacked on as they are
    priority: Any = 0
    uid: Any = 0
    seq: Any = 0
    data = b""
    try:
        while True:
            if end - pos >= HEADER + body:
                head, kind, priority, uid, seq, data = whole(buf, pos)
            elif end - pos >= EVENT_HEADER:
                head, kind, priority, uid, seq, data = _WHOLE[0].unpack_from(buf, pos)
            elif end - pos >= HEADER:
                (head,), kind = unpack_head(buf, pos), 0
            else:
                break
            length = head & MAX_BODY
            if head >> 24 != VERSION:
                raise DecodeError(f"unsupported UPS/TCP version {head >> 24} (this is {VERSION})")
            if length > max_frame:
                raise DecodeError(f"frame of {length} bytes exceeds the limit of {max_frame}")
            start = pos + HEADER
            if end - start < length:
                break
            pos = start + length
            if kind == event and length >= 18:
                if length != 18 + len(data):  # another size than the last event's
                    data = bytes(view[start + 18 : pos])
                    if length - 18 < len(_WHOLE):
                        whole, body = _WHOLE[length - 18].unpack_from, length
                on_event(owner, uid, data, priority, seq)
                continue
            if length and buf[start] == _EVENT:
                raise DecodeError(f"event frame of {length} bytes: at least 18 expected")
            on_frame(owner, _checked(_unpack(view[start:pos])))
            if one_frame:
                break
    finally:
        view.release()
    return pos


def _unpack(body: bytes | memoryview) -> tuple[Any, ...]:
    try:
        fields = msgpack.unpackb(body, use_list=False, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises a variety of types for bad input
        raise DecodeError(f"frame body is not msgpack: {exc}") from None
    if not isinstance(fields, tuple) or not fields or type(fields[0]) is not int:
        raise DecodeError(f"frame body must be an array starting with its kind: {_short(fields)}")
    return fields


def _checked(fields: tuple[Any, ...]) -> Frame:
    try:
        return _frame(fields)
    except (TypeError, ValueError) as exc:
        raise DecodeError(f"bad frame {_short(fields)}: {exc}") from None


def _short(value: Any) -> str:
    """A short description of decoded junk, safe for any depth of nesting."""
    try:
        return reprlib.repr(value)
    except RecursionError:
        return f"<{type(value).__name__} nested too deep>"


def _frame(f: tuple[Any, ...]) -> Frame:
    kind = f[0]
    if kind == _START:
        _, uid, seq = f
        return Start(_uid(uid), _uid(seq))
    if kind == _HELLO:
        _, node_id, name, host, port = f
        return Hello(_uid(node_id), _str(name), _str(host), _int(port, 0xFFFF))
    if kind == _STATUS_READERS:
        _, readers = f
        return StatusReaders(None if readers is None else tuple(map(_str, _array(readers))))
    if kind in (_SUB, _ADVERTISE):
        _, uid, *name = f  # the name is optional
        if len(name) > 1:
            raise ValueError("too many fields")
        named = _str(name[0]) if name and name[0] is not None else None
        return (Subscribe if kind == _SUB else Advertise)(_uid(uid), named)
    if kind in (_UNSUB, _UNADVERTISE):
        _, uid = f
        return (Unsubscribe if kind == _UNSUB else Unadvertise)(_uid(uid))
    if kind == _SUBSCRIBERS:
        _, uid, peers = f
        return Subscribers(_uid(uid), tuple(_peer(p) for p in _array(peers)))
    if kind == _PUBLISHERS:
        _, uid, publishers = f
        return Publishers(_uid(uid), tuple(_voucher(p) for p in _array(publishers)))
    if kind == _REFUSED:
        _, uid, right, reason = f
        if right not in RIGHTS:
            raise ValueError(f"unknown right {right!r:.30}")
        return Refused(_uid(uid), right, _str(reason))
    if kind in (_WATCH, _UNWATCH):
        _, pattern = f
        return (Watch if kind == _WATCH else Unwatch)(_str(pattern))
    if kind == _NAMES:
        _, pattern, channels, done = f
        if type(done) is not bool:
            raise TypeError(f"done must be true or false: {done!r:.30}")
        return Names(_str(pattern), tuple(_named(c) for c in _array(channels)), done)
    if kind in (_PING, _PONG, _STATUS_REQUEST) and len(f) == 1:
        return Ping() if kind == _PING else Pong() if kind == _PONG else StatusRequest()
    if kind == _STATUS:
        _, info = f
        if not isinstance(info, dict) or not all(isinstance(k, str) for k in info):
            raise TypeError("status must be a map with string keys")
        return Status(info)
    raise ValueError(f"unknown frame kind {kind}")


def _array(value: Any) -> tuple[Any, ...]:
    if not isinstance(value, tuple):
        raise TypeError(f"not an array: {_short(value)}")
    return value


def _named(value: Any) -> tuple[int, str]:
    uid, name = _array(value)
    return _uid(uid), _str(name)


def _voucher(value: Any) -> tuple[int, str]:
    node_id, identity = _array(value)
    return _uid(node_id), _str(identity)


def _peer(value: Any) -> Peer:
    node_id, host, port, *rest = _array(value)
    if len(rest) > 1:
        raise ValueError("too many fields in a peer")
    identity = _str(rest[0]) if rest and rest[0] is not None else None
    return Peer(_uid(node_id), _str(host), _int(port, 0xFFFF), identity)


def _uid(value: Any) -> int:
    if type(value) is not int or not 0 <= value < 1 << 64:
        raise ValueError(f"not a 64-bit unsigned integer: {value!r:.30}")
    return value


def _int(value: Any, top: int) -> int:
    if type(value) is not int or not 0 <= value <= top:
        raise ValueError(f"not an integer in 0..{top}: {value!r:.30}")
    return value


def _str(value: Any) -> str:
    if not isinstance(value, str):
        raise TypeError(f"not a string: {value!r:.30}")
    return value
