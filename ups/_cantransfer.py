"""Events larger than one CAN frame: size classes of etags, and the transfer codec.

No I/O here. ``docs/protocol.md`` ("Events larger than one frame") describes the same bytes.

An etag's *size class* says how its channel's events travel and how large they may be:

- class 0 (etags 0x0010-0x2FFF): one frame per event, the frame's data is the event (0-8 bytes),
  exactly as before there were larger events;
- classes 1-4 (1024 etags each from 0x3000): events up to 64 B, 1 KiB, 4 KiB and 65535 B, each
  sent as a *transfer* of one or more frames.

A transfer's frames each start with a header byte ``S E T tid``: S (0x80) on its first frame,
E (0x40) on its last, T (0x20) a toggle that is 1 on the first frame and alternates, and a
5-bit transfer id that the sender counts up per event on each (TxNode, etag). The bytes after
the header bytes, concatenated, are the *stream*: the event's length (u16), the event, and,
when the transfer has more than one frame, the CRC-16/CCITT-FALSE of the event. Every frame but
the last is full (8 bytes classic, 64 CAN FD); the last is as short as its bytes allow, padded
with zeros to the next CAN FD length on FD.
"""

from __future__ import annotations

import binascii
from collections import OrderedDict

from ._canproto import FIRST_ETAG, LARGE_FIRST_ETAG, LAST_ETAG

CLASS_ETAGS = 0x400  #: etags per large size class
CLASS_MAX = (8, 64, 1024, 4096, 0xFFFF)  #: the largest event of each size class, in bytes
MAX_EVENT = CLASS_MAX[-1]
START, END, TOGGLE, TID_MASK = 0x80, 0x40, 0x20, 0x1F
FD_SIZES = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
MAX_TRANSFERS = 64  #: transfers a receiver reassembles at once (the oldest is given up)
TRANSFER_TIMEOUT = 1.0  #: seconds a transfer may wait for its next frame before it is given up


def size_class(etag: int) -> int:
    """The size class of ``etag`` (0: one frame per event)."""
    if etag < LARGE_FIRST_ETAG:
        return 0
    return 1 + ((etag - LARGE_FIRST_ETAG) >> 10)


def class_for(size: int) -> int:
    """The smallest size class whose events may be ``size`` bytes long."""
    for cls, largest in enumerate(CLASS_MAX):
        if size <= largest:
            return cls
    raise ValueError(f"an event on CAN is at most {MAX_EVENT} bytes, not {size}")


def class_etags(cls: int) -> range:
    """The etags of size class ``cls``."""
    if cls == 0:
        return range(FIRST_ETAG, LARGE_FIRST_ETAG)
    first = LARGE_FIRST_ETAG + (cls - 1) * CLASS_ETAGS
    return range(first, min(first + CLASS_ETAGS, LAST_ETAG + 1))


def max_size(etag: int) -> int:
    """The largest event a channel bound to ``etag`` carries."""
    return CLASS_MAX[size_class(etag)]


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (polynomial 0x1021, initial 0xFFFF; "123456789" gives 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


def fd_length(n: int) -> int:
    """The CAN FD data length that carries ``n`` bytes."""
    for size in FD_SIZES:
        if size >= n:
            return size
    raise ValueError(f"a CAN FD frame carries at most 64 bytes, not {n}")


def frames_for(size: int, mtu: int) -> int:
    """How many frames a transfer of a ``size``-byte event takes with ``mtu``-byte frames."""
    chunk = mtu - 1
    if 2 + size <= chunk:
        return 1
    return -(-(2 + size + 2) // chunk)


def segment(event: bytes, tid: int, mtu: int) -> list[bytes]:
    """The data of each frame of the transfer of ``event`` (``mtu``: 8 classic, 64 FD)."""
    size = len(event)
    if size > MAX_EVENT:
        raise ValueError(f"an event on CAN is at most {MAX_EVENT} bytes, not {size}")
    chunk = mtu - 1
    stream = size.to_bytes(2, "big") + event
    if len(stream) > chunk:
        stream += crc16(event).to_bytes(2, "big")
    tid &= TID_MASK
    frames = []
    toggle = TOGGLE
    for at in range(0, len(stream), chunk):
        header = toggle | tid
        if at == 0:
            header |= START
        if at + chunk >= len(stream):
            header |= END
        frames.append(bytes((header,)) + stream[at : at + chunk])
        toggle ^= TOGGLE
    if mtu > 8:
        last = frames[-1]
        frames[-1] = last + bytes(fd_length(len(last)) - len(last))
    return frames


class _Transfer:
    __slots__ = ("buffer", "frames", "length", "mtu", "started", "tid", "toggle")

    def __init__(self, tid: int, length: int, mtu: int, started: float) -> None:
        self.tid = tid
        self.length = length
        self.mtu = mtu
        self.frames = frames_for(length, mtu) - 1  # still to come
        self.toggle = 0  # the first frame had TOGGLE: the next has not
        self.buffer = bytearray()
        self.started = started


class Reassembler:
    """Rebuilds events from the frames of transfers, per sender and etag.

    ``feed`` returns an event when its last frame arrives intact. Whatever cannot be an intact
    event is counted, never returned: ``lost`` counts transfers given up (a missing, repeated or
    out-of-order frame, a bad length or CRC, a stale or evicted transfer) and runs of frames
    whose first frame never came; ``frames_dropped`` counts their frames.
    """

    def __init__(
        self, max_transfers: int = MAX_TRANSFERS, timeout: float = TRANSFER_TIMEOUT
    ) -> None:
        self._open: OrderedDict[tuple[int, int], _Transfer] = OrderedDict()
        self._orphans: OrderedDict[tuple[int, int], int] = OrderedDict()  # key -> tid
        self._max = max_transfers
        self._timeout = timeout
        self.lost = 0
        self.frames_dropped = 0
        self.evicted = 0

    @property
    def pending(self) -> int:
        """Transfers started and not yet complete."""
        return len(self._open)

    def feed(
        self, key: tuple[int, int], data: bytes, fd: bool, largest: int, now: float
    ) -> bytes | None:
        """Take one frame of ``key`` (sender, etag); ``largest`` is the etag's class maximum.
        ``fd``: the frame is a CAN FD frame (its transfer's frames are 64 bytes long)."""
        if not data:
            self._drop_orphan(key, -1)
            return None
        header = data[0]
        if header & START:
            old = self._open.pop(key, None)
            if old is not None:
                self._give_up(old)
            self._orphans.pop(key, None)
            return self._start(key, header, data, 64 if fd else 8, largest, now)
        transfer = self._open.get(key)
        if transfer is None:
            self._drop_orphan(key, header & TID_MASK)
            return None
        last = bool(header & END)
        if (
            header & TID_MASK != transfer.tid
            or header & TOGGLE != transfer.toggle
            or last != (transfer.frames == 1)
            or (fd != (transfer.mtu == 64))
            or (not last and len(data) != transfer.mtu)
        ):
            del self._open[key]
            self._give_up(transfer)
            if header & TID_MASK == transfer.tid:  # the rest of it: dropped, lost once
                self._orphans[key] = transfer.tid
                self.frames_dropped += 1
            else:  # a frame of a transfer whose first frame never came: lost too
                self._drop_orphan(key, header & TID_MASK)
            return None
        transfer.toggle ^= TOGGLE
        transfer.frames -= 1
        transfer.buffer += data[1:]
        transfer.started = now
        if not last:
            self._open.move_to_end(key)
            return None
        del self._open[key]
        stream, length = transfer.buffer, transfer.length
        if _tail_ok(stream, length + 4, transfer.mtu, len(data)):
            event = bytes(stream[2 : 2 + length])
            if crc16(event) == int.from_bytes(stream[2 + length : 4 + length], "big"):
                return event
        self._give_up(transfer)
        return None

    def expire(self, now: float) -> int:
        """Give up every transfer that waited longer than the timeout for its next frame."""
        stale = [k for k, t in self._open.items() if now - t.started > self._timeout]
        for key in stale:
            self._give_up(self._open.pop(key))
        return len(stale)

    def _start(
        self, key: tuple[int, int], header: int, data: bytes, mtu: int, largest: int, now: float
    ) -> bytes | None:
        length = int.from_bytes(data[1:3], "big") if len(data) >= 3 else -1
        single = frames_for(length, mtu) == 1
        if not (
            header & TOGGLE
            and 0 <= length <= largest
            and single == bool(header & END)
            and (single or len(data) == mtu)
        ):
            self.lost += 1
            self.frames_dropped += 1
            return None
        if single:  # no CRC: the CAN frame's own CRC covers it
            if _tail_ok(data, 3 + length, mtu, len(data)):
                return bytes(data[3 : 3 + length])
            self.lost += 1
            self.frames_dropped += 1
            return None
        transfer = _Transfer(header & TID_MASK, length, mtu, now)
        transfer.buffer += data[1:]
        if len(self._open) >= self._max:
            _, oldest = self._open.popitem(last=False)
            self.evicted += 1
            self._give_up(oldest)
        self._open[key] = transfer
        return None

    def _give_up(self, transfer: _Transfer) -> None:
        self.lost += 1
        self.frames_dropped += 1 + len(transfer.buffer) // (transfer.mtu - 1)

    def _drop_orphan(self, key: tuple[int, int], tid: int) -> None:
        self.frames_dropped += 1
        if self._orphans.get(key) != tid:  # a new run of frames without their first
            self._orphans[key] = tid
            if len(self._orphans) > self._max:
                self._orphans.popitem(last=False)
            self.lost += 1


def _tail_ok(stream: bytes | bytearray, total: int, mtu: int, frame_len: int) -> bool:
    """The stream ends at ``total`` bytes, followed by nothing, or on FD by the zeros that pad
    the last frame to a CAN FD length."""
    extra = len(stream) - total
    if extra < 0:
        return False
    if extra == 0:
        return mtu == 8 or frame_len == fd_length(frame_len)
    return mtu == 64 and frame_len == fd_length(frame_len) and not any(stream[total:])
