"""A line of emulated slaves behind one port: an EtherCAT frame (EtherType 0x88A4) passes
through each slave in turn, datagram by datagram, and goes back to the master, as it does
through a line of real slaves whose last one closes the loop.

``process(frame)`` returns the frame the master gets back, or None for what is not an
EtherCAT frame of datagrams (type 1), or is malformed (too short, a datagram past the end):
those are counted and dropped, the way a slave drops a frame with a bad checksum.
"""

from __future__ import annotations

import struct

from ._esc import Slave

ETHERTYPE = 0x88A4
ETH_HEADER, ECAT_HEADER, DATAGRAM_HEADER, WKC = 14, 2, 10, 2
MORE_FOLLOWS = 0x8000


class Chain:
    def __init__(self, slaves: list[Slave]) -> None:
        self.slaves = slaves
        for n, slave in enumerate(slaves):
            slave.set_link(last=n == len(slaves) - 1)
        self.counts = {"frames": 0, "datagrams": 0, "dropped": 0}

    def process(self, frame: bytes) -> bytes | None:
        if len(frame) < ETH_HEADER + ECAT_HEADER + DATAGRAM_HEADER + WKC:
            return self._drop()
        if struct.unpack_from(">H", frame, 12)[0] != ETHERTYPE:
            return self._drop()
        (header,) = struct.unpack_from("<H", frame, ETH_HEADER)
        length, kind = header & 0x07FF, header >> 12
        end = ETH_HEADER + ECAT_HEADER + length
        if kind != 1 or end > len(frame):
            return self._drop()
        out = bytearray(frame)
        at = ETH_HEADER + ECAT_HEADER
        while True:
            if at + DATAGRAM_HEADER + WKC > end:
                return self._drop()
            command, _index, adp, ado, size, _irq = struct.unpack_from("<BBHHHH", out, at)
            data_at = at + DATAGRAM_HEADER
            data_end = data_at + (size & 0x07FF)
            if data_end + WKC > end:
                return self._drop()
            data = bytearray(out[data_at:data_end])
            (wkc,) = struct.unpack_from("<H", out, data_end)
            for slave in self.slaves:
                adp, wkc = slave.datagram(command, adp, ado, data, wkc)
            struct.pack_into("<H", out, at + 2, adp)
            out[data_at:data_end] = data
            struct.pack_into("<H", out, data_end, wkc & 0xFFFF)
            self.counts["datagrams"] += 1
            at = data_end + WKC
            if not size & MORE_FOLLOWS:
                break
        out[6] |= 0x02  # the source address's locally administered bit, as port 0 sets it
        self.counts["frames"] += 1
        return bytes(out)

    def _drop(self) -> bytes | None:
        """Count a frame dropped; what ``process`` returns for it (None)."""
        self.counts["dropped"] += 1
        return None
