"""The gateway's tap: the first events of a channel it does not forward to the IP side yet.

A gateway that hosts the serving CAN-ECB holds a new publisher's binding until it forwards the
channel (the CAN-ECB's bind gate). One that does not (``--external-can-ecb``, or its CAN-ECB
stands by) cannot: a publisher sends its first events the moment the CAN-ECB's Bind goes out
(or with its PUB_AT, on an etag it holds already), while the gateway still asks the IP side
who subscribes. The tap keeps them. From a Bind or PUB_AT it hears of a channel it does not
forward to IP, it keeps that etag's event frames, and when the gateway then forwards the
channel it hands them over first, in order, and forwards what comes next itself, until the
gateway's CAN face receives the etag. The handover is exact: an event frame is the tap's until
the face receives the etag, which it starts to do on the answer to its own SUB_BIND, a frame
earlier in the same ordered stream; so each frame is forwarded once.

The tap takes in every event frame of the bus while it is wide open (``wide``): a kernel
filter widened only once the Bind is heard would come too late for the frames right behind it.
The gateway opens it while it does not host the serving CAN-ECB, and closes it otherwise (its
CAN-ECB's bind gate does the tap's work); closed, it costs nothing.

Bounds: ``TAP_ETAGS`` etags tapped at once (a Bind beyond is not tapped: ``tap_full``),
``TAP_FRAMES`` frames kept per etag (more are dropped, counted in ``tap_dropped``), and
``TAP_TIME`` s for the gateway to decide (then what nobody wanted is dropped, not counted: no
one subscribed).
Only one-frame etags (below 0x3000) are tapped; a large event's transfer is not.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import can

from ups import _canproto as p
from ups._canlink import CanLink
from ups._errors import DecodeError

TAP_ETAGS = 64  #: etags tapped at once
TAP_FRAMES = 256  #: frames kept per tapped etag until the gateway decides
TAP_TIME = 2.0  #: seconds the gateway has to decide about a tapped channel

#: Bind (priority 0x01, TxNode 0x7F) and PUB_AT (priority 0x01, a node's TxNode)
_PRIORITY_1 = [{"can_id": 1 << p.PRIORITY_SHIFT, "can_mask": 0xFF << p.PRIORITY_SHIFT,
                "extended": True}]  # fmt: skip

Send = Callable[[bytes, int], None]  # data, priority


class _Tapped:
    __slots__ = ("frames", "send", "since", "uid")

    def __init__(self, uid: int, since: float) -> None:
        self.uid = uid
        self.since = since
        self.frames: list[tuple[bytes, int]] = []
        self.send: Send | None = None  # set once the gateway forwards the channel


class Tap:
    """Taps ``link`` for the gateway. ``forwarding(uid)``: whether the gateway forwards the
    channel to IP already; ``receives(etag)``: whether its CAN face receives the etag itself;
    ``own()``: its CAN face's TxNode (its own frames are never tapped)."""

    def __init__(
        self,
        link: CanLink,
        *,
        forwarding: Callable[[int], bool],
        receives: Callable[[int], bool],
        own: Callable[[], int | None],
        counters: dict[str, int],
    ) -> None:
        self._link = link
        self._forwarding = forwarding
        self._receives = receives
        self._own = own
        self._counters = counters
        self._taps: dict[int, _Tapped] = {}  # etag -> what it keeps
        self._expiry: asyncio.TimerHandle | None = None
        self._wide = False
        counters.update(tapped=0, tap_dropped=0, tap_full=0)

    def start(self) -> None:
        self._link.add_handler(self._on_announcement, _PRIORITY_1)
        self._link.add_handler(self._on_event, [])

    def wide(self, on: bool) -> None:
        """Take in every event frame (on), or none (off: what it keeps is dropped)."""
        if on != self._wide:
            self._wide = on
            self._link.set_filters(self._on_event, None if on else [])
            if not on:
                self._taps.clear()

    def close(self) -> None:
        self._link.remove_handler(self._on_announcement)
        self._link.remove_handler(self._on_event)
        self._taps.clear()
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None

    def forward(self, uid: int, send: Send) -> None:
        """The gateway forwards ``uid`` now: what was kept goes first, then what comes."""
        for tapped in self._taps.values():
            if tapped.uid == uid and tapped.send is None:
                tapped.send = send
                for data, priority in tapped.frames:
                    send(data, priority)
                self._counters["tapped"] += len(tapped.frames)
                tapped.frames.clear()

    def drop(self, uid: int) -> None:
        """The gateway decided about ``uid``: its CAN face receives it, or nobody wants it."""
        for etag in [etag for etag, tapped in self._taps.items() if tapped.uid == uid]:
            del self._taps[etag]

    def _on_announcement(self, frame: can.Message) -> None:
        can_id = frame.arbitration_id
        if not frame.is_extended_id or frame.is_fd or not p.is_management(can_id):
            return
        try:
            msg = p.decode(can_id, bytes(frame.data))
        except DecodeError:
            return
        if isinstance(msg, p.Bind) or (isinstance(msg, p.Holds) and msg.publish):
            self._begin(msg.etag, msg.uid)

    def _begin(self, etag: int, uid: int) -> None:
        if not self._wide or etag >= p.LARGE_FIRST_ETAG or self._forwarding(uid):
            return
        if self._receives(etag):
            return
        tapped = self._taps.get(etag)
        if tapped is not None and tapped.uid == uid:
            return
        if tapped is None and len(self._taps) >= TAP_ETAGS:
            self._counters["tap_full"] += 1  # its first events may go unforwarded
            return
        self._taps[etag] = _Tapped(uid, time.monotonic())  # (an etag bound anew: start over)
        if self._expiry is None:
            self._expiry = asyncio.get_running_loop().call_later(TAP_TIME, self._expire)

    def _on_event(self, frame: can.Message) -> None:
        can_id = frame.arbitration_id
        etag = can_id & p.ETAG_MASK
        tapped = self._taps.get(etag)
        if tapped is None or p.is_management(can_id) or frame.is_fd:
            return
        if self._receives(etag):  # the face has it from this frame on: the tap is done
            del self._taps[etag]
            return
        if (can_id >> p.TXNODE_SHIFT) & p.TXNODE_MASK == self._own() or len(frame.data) > 8:
            return
        data, priority = bytes(frame.data), can_id >> p.PRIORITY_SHIFT
        if tapped.send is not None:
            self._counters["tapped"] += 1
            tapped.send(data, priority)
        elif len(tapped.frames) < TAP_FRAMES:
            tapped.frames.append((data, priority))
        else:
            self._counters["tap_dropped"] += 1

    def _expire(self) -> None:
        self._expiry = None
        now = time.monotonic()
        old = [e for e, t in self._taps.items() if t.send is None and now - t.since >= TAP_TIME]
        for etag in old:
            del self._taps[etag]
        if self._taps:
            self._expiry = asyncio.get_running_loop().call_later(TAP_TIME / 2, self._expire)
