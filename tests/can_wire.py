"""A python-can bus of a test's own on a UPS bus: it sends frames as a forger would, and keeps
every management frame it hears, with when it heard it (a thread reads the bus)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import can

from ups import _canproto as p
from ups._canlink import open_bus
from ups._errors import DecodeError


class Wire:
    def __init__(self, bus: str) -> None:
        self.raw = open_bus(bus)
        self.frames: list[tuple[float, p.Management]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            frame = self.raw.recv(0.05)
            if frame is None or not frame.is_extended_id:
                continue
            if not p.is_management(frame.arbitration_id):
                continue
            try:
                msg = p.decode(frame.arbitration_id, bytes(frame.data))
            except DecodeError:
                continue
            with self._lock:
                self.frames.append((time.monotonic(), msg))

    def send(self, msg: p.Management) -> float:
        """Put ``msg`` on the bus; when it was sent."""
        can_id, data = p.encode(msg)
        sent = time.monotonic()
        self.raw.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))
        return sent

    def heard(self, since: float = 0.0) -> list[p.Management]:
        """The management frames heard since ``since`` (a ``time.monotonic()``), in order."""
        with self._lock:
            return [msg for at, msg in self.frames if at >= since]

    def close(self) -> None:
        self._stop.set()
        self._reader.join(timeout=5)
        self.raw.shutdown()


@contextmanager
def wire(bus: str) -> Iterator[Wire]:
    listener = Wire(bus)
    try:
        yield listener
    finally:
        listener.close()
