"""A daemon's status on TCP: answers a StatusRequest frame with a Status frame (the TCP/IP
framing of ``docs/protocol.md``), so ``ups status`` and ``ups ls`` can ask it.

For the standalone CAN-ECB (``ups can-broker --status HOST:PORT``), which has no TCP face of
its own. It answers only status: every other frame ends the link (``status_bad_requests``),
and a link that was answered is closed. Admission is ``ups/_port.py``'s: ``MAX_LINKS`` links
served at once, each ``READ_TIMEOUT`` seconds to ask and ``ANSWER_TIMEOUT`` to be answered
(``status_timed_out``); newcomers are let in in the order they came, ``MAX_WAITING`` of them
waiting in line ``WAIT_TIMEOUT`` at most (``status_refused_busy``); while someone waits, a
link that has not asked ``TURN`` seconds after it was let in gives way (``status_evicted``).
So links that never ask, trickle, or ask and reconnect at once cannot keep a real request
out: whoever asks is answered within ``PROMISE`` seconds (docs/security.md says against how
many). The Status is built at most once per ``STATUS_GAP`` seconds however many ask
(``StatusPacer``), and carries these counters in its ``stats``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from ups import _tcpwire as w
from ups._address import parse_address
from ups._errors import ConfigError, DecodeError
from ups._port import BadRequest, Limits, Port, listen
from ups._statuspacer import StatusPacer

log = logging.getLogger("ups.status")

MAX_LINKS = 64  #: status links served at once
MAX_WAITING = 64  #: links waiting in line for a slot, at most (the next wait unaccepted)
TURN = 0.5  #: seconds a link idle (not asking, not reading) keeps its slot while others wait
READ_TIMEOUT = 2.0  #: seconds a link may take to ask, once let in
ANSWER_TIMEOUT = 5.0  #: seconds an answer may take to be built and written
WAIT_TIMEOUT = 5.0  #: seconds a link waits in line at most
MAX_REQUEST = 1024  #: bytes: a StatusRequest is a few
PROMISE = 5.0  #: seconds: whoever asks is answered within this (docs/security.md)


class StatusServer:
    """Serves ``info()`` to whoever asks, on ``address``; ``counters`` (``status_...``) are
    added to the ``stats`` of what it serves."""

    def __init__(self, address: str, info: Callable[[], dict[str, Any]]) -> None:
        self.host, self.port = parse_address(address)
        self._info = info
        limits = Limits(links=MAX_LINKS, waiting=MAX_WAITING, turn=TURN,
                        read_timeout=READ_TIMEOUT, answer_timeout=ANSWER_TIMEOUT,
                        wait_timeout=WAIT_TIMEOUT, max_request=MAX_REQUEST)  # fmt: skip
        self._port = Port("the status port", _request_reader, self._answer, limits)
        self._paced: dict[str, int] = {}  # the pacer's: status_builds, _answers, _paced
        self._pacer = StatusPacer(self._served, self._paced, who="the status port")

    @property
    def counters(self) -> dict[str, int]:
        """The port's counters, as ``ups status`` and the metrics show them."""
        port = self._port.counters
        return {
            "status_refused_busy": port["refused_busy"],
            "status_evicted": port["evicted"],
            "status_timed_out": port["timed_out"],
            "status_bad_requests": port["bad_requests"],
            "status_builds": self._paced["status_builds"],
            "status_answers": port["answers"],
            "status_paced": self._paced["status_paced"],
        }

    async def start(self) -> None:
        try:
            sock = listen(self.host, self.port)
        except OSError as exc:
            raise ConfigError(
                f"cannot serve the status on {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        await self._port.start(sock)
        self.port = self._port.port
        log.info("status on %s:%d", self.host, self.port)

    async def close(self) -> None:
        self._pacer.close()  # answers still awaited end too
        await self._port.close()

    def _served(self) -> dict[str, Any]:
        info = self._info()
        return {**info, "stats": {**info.get("stats", {}), **self.counters}}

    async def _answer(self, request: bool) -> bytes:
        return await self._pacer.next_frame()


def _request_reader() -> Callable[[bytes], bool | None]:
    """A link's reader: True once it sent a StatusRequest; any other frame is a bad request."""
    decoder = w.Decoder(max_frame=MAX_REQUEST)

    def feed(data: bytes) -> bool | None:
        try:
            frames = decoder.feed(data)
        except DecodeError:
            raise BadRequest() from None
        if any(not isinstance(f, w.StatusRequest) for f in frames):
            raise BadRequest()
        return True if frames else None

    return feed
