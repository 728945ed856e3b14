"""The OCU of ``benchmarks/jaus_paper000``: JAUS from the benchmark's process on one UDP
socket, read by its event loop, and what it recognises in what comes back (ACKs by sequence
number, payloads by code, the authority an Event reports)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import Callable
from typing import Any

OCU_ID = (200, 1, 1)
SETUP_TIMEOUT = 60.0


class Ocu:
    """A JAUS operator control unit on one UDP socket, read by the event loop; each datagram is
    stamped (``perf_counter_ns``) as soon as the loop sees it."""

    def __init__(self, target: tuple[str, int], component: tuple[int, int, int]) -> None:
        from ups.jaus import JausId

        self.me, self.to = JausId(*OCU_ID), JausId(*component)
        self.target = target
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.inbox: asyncio.Queue[tuple[int, bytes]] = asyncio.Queue()
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.sock.fileno(), self._readable)

    def close(self) -> None:
        self._loop.remove_reader(self.sock.fileno())
        self.sock.close()

    def _readable(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                return
            self.inbox.put_nowait((time.perf_counter_ns(), data))

    def send(self, payload: Any, *, sequence: int = 0, ack: bool = False) -> int:
        """Send ``payload`` in JUDP; the size of its message (header, code, payload)."""
        from ups.jaus import AckNak, JudpHeader, JudpMessage, encode_judp, encode_payload

        code, body = encode_payload(payload)
        header = JudpHeader(
            destination=self.to,
            source=self.me,
            sequence=sequence,
            ack_nak=AckNak.REQUEST if ack else AckNak.NONE,
        )
        datagram = encode_judp([JudpMessage(header, code, body)])
        self.sock.sendto(datagram, self.target)
        return len(datagram) - 1  # the transport's version byte is not the message

    def send_ra33(self, payload: Any, *, sequence: int, ack: bool) -> int:
        """Send ``payload`` in RA 3.3 framing; the size of its message (header and payload)."""
        from ups.jaus import (
            RA33_PREFIX,
            AckNak,
            Ra33Address,
            Ra33Header,
            Ra33Message,
            encode_ra33,
            encode_ra33_payload,
        )

        code, body = encode_ra33_payload(payload)
        header = Ra33Header(
            code,
            Ra33Address(self.to.subsystem, self.to.node, self.to.component),
            Ra33Address(self.me.subsystem, self.me.node, self.me.component),
            ack_nak=AckNak.REQUEST if ack else AckNak.NONE,
            sequence=sequence,
        )
        datagram = encode_ra33(Ra33Message(header, body))
        self.sock.sendto(datagram, self.target)
        return len(datagram) - len(RA33_PREFIX)

    async def receive(self, want: Callable[[bytes], Any], timeout: float) -> tuple[int, Any]:
        """(arrival ns, what ``want`` made of it) for the first datagram it accepts (returns
        non-None for); others are skipped. TimeoutError when none comes in time."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            arrived, data = await asyncio.wait_for(self.inbox.get(), left)
            found = want(data)
            if found is not None:
                return arrived, found
        raise TimeoutError

    def drain(self) -> int:
        n = 0
        while not self.inbox.empty():
            self.inbox.get_nowait()
            n += 1
        return n

    async def ask(self, payload: Any, answer: type) -> Any:
        self.send(payload)
        return (await self.receive(lambda d: payload_of(d, answer), SETUP_TIMEOUT / 4))[1]


def judp_ack(data: bytes, sequence: int) -> bool | None:
    from ups.jaus import AckNak, JausDecodeError, decode_judp

    with contextlib.suppress(JausDecodeError):
        for msg in decode_judp(data):
            if msg.header.ack_nak == AckNak.ACK and msg.header.sequence == sequence:
                return True
    return None


def ra33_ack(data: bytes, sequence: int) -> bool | None:
    from ups.jaus import RA33_PREFIX, AckNak, JausDecodeError, decode_ra33

    if data.startswith(RA33_PREFIX):
        with contextlib.suppress(JausDecodeError):
            h = decode_ra33(data).header
            if h.ack_nak == AckNak.ACK and h.sequence == sequence:
                return True
    return None


def payload_of(data: bytes, kind: type) -> Any:
    from ups.jaus import JausDecodeError, decode_judp, decode_payload

    with contextlib.suppress(JausDecodeError):
        for msg in decode_judp(data):
            if msg.code is not None and msg.code == getattr(kind, "CODE", None):
                return decode_payload(msg.code, msg.payload)
    return None


def event_value(data: bytes, event_id: int) -> int | None:
    """The authority an Event of ``event_id`` reports, else None."""
    from ups.jaus import Event, MessageCode

    event = payload_of(data, Event)
    if event is None or event.event_id != event_id:
        return None
    report = event.report_message
    if int.from_bytes(report[:2], "little") != MessageCode.REPORT_AUTHORITY or len(report) < 3:
        return None
    return int(report[2])
