"""Large JUDP messages put back together from their FIRST, NORMAL ... LAST parts.

Pure: the caller passes the time (``now``, seconds of a monotonic clock); nothing here reads a
clock or a socket. ``docs/jaus.md`` ("Reassembly") states the rules and the bounds.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, replace

from ._codec import RESPONSES, JausId
from ._judp import CODE_SIZE, DataFlags, JudpMessage, rules_error

DEFAULT_TIMEOUT = 10.0  #: seconds a part waits for the rest of its message (Junior's default)
MAX_PARTS = 100  #: parts held at once, over every sender (Junior's default history)
MAX_PENDING_BYTES = 1 << 20  #: transported bytes held at once
MAX_MESSAGE_BYTES = 1 << 20  #: the largest message rebuilt (code and payload)

_Key = tuple[JausId, JausId]  # (source, destination)


@dataclass(slots=True)
class ReassemblyCounts:
    """What a :class:`Reassembler` did with the parts it was fed.

    Every part fed is, at any time, exactly one of: used in a rebuilt message
    (``parts_used``), held (``Reassembler.pending``), or dropped for one reason
    (``dropped`` is their sum).
    """

    parts_in: int = 0  #: NORMAL/FIRST/LAST parts fed
    parts_used: int = 0  #: parts that went into rebuilt messages
    messages: int = 0  #: messages rebuilt
    expired: int = 0  #: parts dropped: waited longer than the timeout
    evicted: int = 0  #: parts dropped to stay within the bounds (oldest first)
    duplicate: int = 0  #: parts dropped: equal to one held, or to one of a rebuilt message
    conflicting: int = 0  #: parts dropped: two different parts with one sequence number
    oversized: int = 0  #: parts dropped: their message would exceed the largest size
    mismatched: int = 0  #: parts dropped: a chain whose parts disagree (priority, code)

    @property
    def dropped(self) -> int:
        return (
            self.expired + self.evicted + self.duplicate + self.conflicting + self.oversized
            + self.mismatched
        )  # fmt: skip


class _Part:
    __slots__ = ("arrived", "message", "size")

    def __init__(self, message: JudpMessage, size: int, arrived: float) -> None:
        self.message = message
        self.size = size
        self.arrived = arrived


class Reassembler:
    """Rebuilds large messages from their parts; never returns a message it is not sure of.

    Parts are grouped by (source, destination). A message is rebuilt when a FIRST part at
    sequence number s, NORMAL parts at s+1 ... and a LAST part at s+k (mod 65536) are all held:
    the sender numbers the messages it sends consecutively, so such a run is exactly one
    message. A missing, conflicting or mismatched part makes the run never complete; its parts
    are dropped when they expire. ``feed`` returns every other message (SINGLE ones, ACK/NAK
    responses) unchanged. ``counts`` says what was dropped and why.
    """

    def __init__(
        self,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        max_parts: int = MAX_PARTS,
        max_bytes: int = MAX_PENDING_BYTES,
        max_message: int = MAX_MESSAGE_BYTES,
        code_in_every_part: bool = False,
    ) -> None:
        if timeout <= 0 or max_parts < 1 or max_bytes < 1 or max_message < CODE_SIZE:
            raise ValueError("the timeout and the bounds must be positive")
        self._timeout = timeout
        self._max_parts = max_parts
        self._max_bytes = max_bytes
        self._max_message = max_message
        self._repeated_code = code_in_every_part
        self._streams: dict[_Key, dict[int, _Part]] = {}
        self._order: OrderedDict[tuple[_Key, int], None] = OrderedDict()  # arrival order
        self._bytes = 0
        # messages rebuilt lately: (key, {sequence: hash of the part}, when), to spot late copies
        self._recent: deque[tuple[_Key, dict[int, int], float]] = deque(maxlen=max_parts)
        self.counts = ReassemblyCounts()

    @property
    def pending(self) -> int:
        """Parts held, waiting for the rest of their message."""
        return len(self._order)

    @property
    def pending_bytes(self) -> int:
        return self._bytes

    def feed(self, message: JudpMessage, now: float) -> JudpMessage | None:
        """Take one decoded message; return a whole message when there is one."""
        self.expire(now)
        header = message.header
        if header.data_flags == DataFlags.SINGLE or header.ack_nak in RESPONSES:
            return message
        problem = rules_error(header, message.code, len(message.payload))
        if problem:
            raise ValueError(f"not a message decode_judp returns: {problem}")
        self.counts.parts_in += 1
        key = (header.source, header.destination)
        seq = header.sequence
        size = len(message.payload) + (CODE_SIZE if message.code is not None else 0)
        if size > self._max_message or size > self._max_bytes:
            self.counts.oversized += 1
            return None
        if self._seen_in_recent(key, seq, message):
            self.counts.duplicate += 1
            return None
        stream = self._streams.setdefault(key, {})
        held = stream.get(seq)
        if held is not None:
            if held.message == message:
                self.counts.duplicate += 1
            else:  # which of the two is right cannot be known: neither is used
                self._remove(key, seq)
                self.counts.conflicting += 2
            return None
        stream[seq] = _Part(message, size, now)
        self._order[(key, seq)] = None
        self._bytes += size
        while len(self._order) > self._max_parts or self._bytes > self._max_bytes:
            oldest_key, oldest_seq = next(iter(self._order))
            self._remove(oldest_key, oldest_seq)
            self.counts.evicted += 1
        if (key, seq) not in self._order:
            return None
        return self._complete(key, seq, now)

    def expire(self, now: float) -> int:
        """Drop the parts that waited longer than the timeout; return how many."""
        dropped = 0
        limit = now - self._timeout
        while self._order:
            key, seq = next(iter(self._order))
            if self._streams[key][seq].arrived >= limit:
                break
            self._remove(key, seq)
            dropped += 1
        while self._recent and self._recent[0][2] < limit:
            self._recent.popleft()
        self.counts.expired += dropped
        return dropped

    def _seen_in_recent(self, key: _Key, seq: int, message: JudpMessage) -> bool:
        digest = hash(message)
        return any(k == key and parts.get(seq) == digest for k, parts, _ in self._recent)

    def _remove(self, key: _Key, seq: int) -> _Part:
        stream = self._streams[key]
        part = stream.pop(seq)
        if not stream:
            del self._streams[key]
        del self._order[(key, seq)]
        self._bytes -= part.size
        return part

    def _complete(self, key: _Key, seq: int, now: float) -> JudpMessage | None:
        stream = self._streams[key]
        first = self._walk(stream, seq, -1)
        last = self._walk(stream, seq, +1)
        if first is None or last is None:
            return None
        count = ((last - first) & 0xFFFF) + 1
        chain = [self._remove(key, (first + i) & 0xFFFF) for i in range(count)]
        head = chain[0].message
        code = head.code or 0  # never None: feed checked that a FIRST part has its code
        code_bytes = code.to_bytes(2, "little")
        pieces = [head.payload]
        agree = True
        for part in chain[1:]:
            other, piece = part.message.header, part.message.payload
            if (other.priority, other.broadcast) != (head.header.priority, head.header.broadcast):
                agree = False
                break
            if self._repeated_code:
                if piece[:CODE_SIZE] != code_bytes:
                    agree = False
                    break
                piece = piece[CODE_SIZE:]
            pieces.append(piece)
        if not agree:
            self.counts.mismatched += count
            return None
        payload = b"".join(pieces)
        if CODE_SIZE + len(payload) > self._max_message:
            self.counts.oversized += count
            return None
        self.counts.parts_used += count
        self.counts.messages += 1
        self._recent.append((key, {p.message.header.sequence: hash(p.message) for p in chain}, now))
        return JudpMessage(replace(head.header, data_flags=DataFlags.SINGLE), code, payload)

    @staticmethod
    def _walk(stream: dict[int, _Part], seq: int, step: int) -> int | None:
        """From ``seq``, the sequence number of the FIRST part (step -1) or of the LAST part
        (step +1) of an unbroken run of held parts, or None."""
        end, stop = DataFlags.FIRST, DataFlags.LAST
        if step > 0:
            end, stop = stop, end
        s = seq
        for _ in range(len(stream)):
            part = stream.get(s)
            if part is None:
                return None
            flags = part.message.header.data_flags
            if flags == end:
                return s
            if flags == stop and s != seq:
                return None  # the end of another message: the run is broken
            s = (s + step) & 0xFFFF
        return None
