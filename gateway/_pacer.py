"""The gateway's TCP->CAN side: what the IP side sends to the bus waits in a queue of
``limit`` events, drained no faster than the bus's bit rate carries it (a token bucket of bus
time, worst-case stuffed frame lengths, every frame of an event larger than one frame). When
the queue is full the oldest event is dropped, and counted (``can_dropped``). An event larger
than its channel's size class on the bus moves the channel to a larger class first
(``CanFace.grow``); one that cannot move is counted (``too_large_for_can``) and skipped."""

from __future__ import annotations

import asyncio
import collections
import logging
from typing import Any

from ups import _canproto as p
from ups import _cantransfer as sizes
from ups._errors import UpsError
from ups._face import ChannelState
from ups.rt import frame_bits

log = logging.getLogger("ups.gateway")

_BURST = 4  # frames the pacer may send back to back after an idle spell


class Pacer:
    """The TCP->CAN queue of a gateway whose CAN face is ``face`` (a bus of ``bitrate`` bit/s,
    CAN FD if ``fd``); ``counters`` is the gateway's (to_can, can_dropped, too_large_for_can,
    pacer_errors)."""

    def __init__(
        self, face: Any, *, bitrate: int, fd: bool, limit: int, counters: dict[str, int]
    ) -> None:
        self._face = face
        self._bitrate = bitrate
        self._fd = fd
        self._limit = limit
        self._counters = counters
        self._queue: collections.deque[tuple[ChannelState, bytes, int]] = collections.deque()
        self._wake = asyncio.Event()

    def __len__(self) -> int:
        """Events waiting."""
        return len(self._queue)

    def put(self, state: ChannelState, data: bytes, priority: int) -> None:
        """Queue an event for the bus (the oldest goes when the queue is full)."""
        if len(data) > sizes.MAX_EVENT:
            self._counters["too_large_for_can"] += 1
            return
        queue = self._queue
        if len(queue) >= self._limit:
            queue.popleft()
            self._counters["can_dropped"] += 1
        queue.append((state, data, priority))
        self._wake.set()

    async def run(self) -> None:
        """Send the queue no faster than the bus carries it (token bucket), until cancelled."""
        loop = asyncio.get_running_loop()
        bits_per_s = float(self._bitrate)
        fd = self._fd
        mtu = 64 if fd else 8
        full = frame_bits(mtu, 29, "worst", fd)
        capacity = float(_BURST * full)  # the bucket holds bus time, in bits
        tokens = capacity
        last = loop.time()
        queue = self._queue
        while True:
            if not queue:
                self._wake.clear()
                await self._wake.wait()
            now = loop.time()
            tokens = min(capacity, tokens + (now - last) * bits_per_s)
            last = now
            while queue:
                state, data, priority = queue[0]
                if len(data) > state.max_size and not await self._grow(state, len(data)):
                    queue.popleft()
                    continue
                if len(data) <= p.CLASSIC_MAX_DATA and state.max_size <= p.CLASSIC_MAX_DATA:
                    cost = frame_bits(len(data), 29, "worst", fd)
                else:
                    cost = sizes.frames_for(len(data), mtu) * full
                wanted = min(cost, capacity)  # an event longer than the bucket: go into debt
                if tokens < wanted:
                    await asyncio.sleep((wanted - tokens) / bits_per_s)
                    break
                tokens -= cost
                queue.popleft()
                try:
                    self._face.send(state, data, priority)
                except Exception:  # one bad frame must not stop TCP->CAN for every channel
                    self._counters["pacer_errors"] += 1
                    log.exception("could not send a TCP->CAN frame on %s", state.channel)
                    continue
                self._counters["to_can"] += 1

    async def _grow(self, state: ChannelState, size: int) -> bool:
        """Move ``state``'s channel to a size class that carries ``size`` bytes on the bus."""
        try:
            await self._face.grow(state, size)
        except UpsError as exc:  # no etag of that class left, the CAN-ECB does not answer...
            self._counters["too_large_for_can"] += 1
            log.warning("cannot forward a %d-byte event of %s: %s", size, state.channel, exc)
            return False
        return True
