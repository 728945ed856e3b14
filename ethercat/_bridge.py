"""The UPS side of ``ups ethercat``: a node whose subscriptions set the segment's outputs, whose
publications carry its inputs, and which publishes the segment's status.

An output channel's event is decoded with the catalog's layout and each mapped field packed
into its bytes (a value beyond the type's range is saturated and counted ``clipped``; an event
that does not fit the layout is counted ``malformed`` and changes nothing). Inputs come from
the cycle's thread through ``call_soon_threadsafe``, at most one hand-over waiting at a time:
what comes meanwhile replaces what waits (counted ``coalesced`` by the segment), so a busy
event loop never holds the cycle back nor piles work up. The status channel carries
:data:`STATUS_LAYOUT` once a second.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import threading
from typing import Any

from ups import DecodeError, Message, Node
from ups._catalog import ChannelSpec

from ._cycle import Segment
from ._map import InputChannel, Output

log = logging.getLogger("ups.ethercat")

STATUS_PERIOD = 1.0  #: s between two status events
#: the status event (little-endian): cycles, late, lost, wkc_errors, left_op, recoveries,
#: silent (u32 each), expected_wkc, last_wkc (u16; 0: no answer), slaves, slaves in OP (u8),
#: 2 bytes zero
STATUS_LAYOUT = struct.Struct("<7I2H2B2x")
STATUS_FIELDS = (
    "cycles", "late", "lost", "wkc_errors", "left_op", "recoveries", "silent", "expected_wkc",
    "last_wkc", "slaves", "in_op",
)  # fmt: skip


class EthercatNode:
    """Connects ``segment`` (started) to ``node`` (open) until :meth:`close`."""

    def __init__(self, node: Node, segment: Segment) -> None:
        self.node = node
        self.segment = segment
        self.counts = {"outputs": 0, "malformed": 0, "clipped": 0, "published": 0}
        self._loop = asyncio.get_running_loop()
        self._waiting: dict[InputChannel, bytes] = {}
        self._lock = threading.Lock()
        self._handing = False
        self._tasks: list[asyncio.Task[None]] = []

    async def start(self) -> None:
        emap = self.segment.map
        for spec, outputs in emap.output_channels().items():
            await self.node.subscribe(spec.channel, callback=self._on_output(spec, outputs))
        for channel in emap.inputs:
            if channel.priority is not None:
                self.node.set_priority(channel.spec.channel, channel.priority)
            await self.node.advertise(channel.spec.channel, max_size=channel.spec.size or 0)
        await self.node.advertise(emap.status, max_size=STATUS_LAYOUT.size)
        self.segment.on_inputs = self._from_cycle
        self._tasks.append(asyncio.create_task(self._publish_status()))

    async def close(self) -> None:
        self.segment.on_inputs = lambda payloads: None
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def status(self) -> dict[str, Any]:
        return {"ethercat": {**self.segment.status(), **self.counts}}

    def status_payload(self) -> bytes:
        s = self.segment.status()
        return STATUS_LAYOUT.pack(*(min(max(0, int(s[k])), _MAX[k]) for k in STATUS_FIELDS))

    # --- outputs --------------------------------------------------------------------------

    def _on_output(self, spec: ChannelSpec, outputs: list[Output]) -> Any:
        def on_event(msg: Message) -> None:
            try:
                values = spec.decode(msg.data)
            except DecodeError:
                self.counts["malformed"] += 1
                return
            for entry in outputs:
                raw, clipped = entry.pack(float(values[entry.field]))
                self.counts["clipped"] += clipped
                self.segment.set_output(entry, raw)
            self.counts["outputs"] += 1

        return on_event

    # --- inputs ---------------------------------------------------------------------------

    def _from_cycle(self, payloads: dict[InputChannel, bytes]) -> None:
        """On the cycle's thread: hand ``payloads`` to the loop, never waiting for it."""
        with self._lock:
            replaced = sum(1 for c in payloads if c in self._waiting)
            self._waiting.update(payloads)
            handing, self._handing = self._handing, True
        self.segment.counts["coalesced"] += replaced
        if not handing:
            with contextlib.suppress(RuntimeError):  # the loop closed: nothing to publish to
                self._loop.call_soon_threadsafe(self._publish_inputs)

    def _publish_inputs(self) -> None:
        with self._lock:
            waiting, self._waiting = self._waiting, {}
            self._handing = False
        for channel, payload in waiting.items():
            try:
                self.node.publish_nowait(channel.spec.channel, payload)
            except Exception as exc:  # closed, or a network error: counted by the node
                log.warning("could not publish %s: %s", channel.spec.channel, exc)
                continue
            self.counts["published"] += 1

    async def _publish_status(self) -> None:
        name = self.segment.map.status
        while True:
            await asyncio.sleep(STATUS_PERIOD)
            try:
                self.node.publish_nowait(name, self.status_payload())
            except Exception as exc:
                log.warning("could not publish the status on %s: %s", name, exc)


_MAX = {k: 0xFFFFFFFF for k in STATUS_FIELDS} | {
    "expected_wkc": 0xFFFF, "last_wkc": 0xFFFF, "slaves": 0xFF, "in_op": 0xFF,
}  # fmt: skip
