"""``ups jaus``: a JAUS component on a UPS node, over JUDP.

A first step of the component host: it answers what any JAUS operator control unit (OCU)
asks first and lets one of them drive the robot through the mapping file.

- AccessControl: Request Control (granted when nobody holds control, when the holder asks
  again, or when the asker's authority is higher; else Confirm Control "not available" or
  "insufficient authority"), Release Control (Reject Control "control released"), Query
  Control (Report Control: the holder and its authority). Control lapses when its holder has
  sent nothing for ``control_timeout`` seconds.
- Liveness: Query Heartbeat Pulse -> Report Heartbeat Pulse.
- Discovery: Query Identification -> Report Identification (the component's name).
- The mapping's commands (``Set…``): published on their channel, only from the controlling
  OCU; from anyone else they are counted (``refused_without_control``) and dropped.
- The mapping's reports: a ``Query…`` is answered from the channel's latest event; before
  any has arrived it is counted (``not_yet``) and left unanswered (JAUS has no error reply).

Bad datagrams are counted (``malformed``), messages this host does not serve too
(``unserved``); parts of large messages go through a bounded ``Reassembler``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ._codec import JausDecodeError, JausId
from ._codes import MessageCode
from ._judp import JudpHeader, JudpMessage, decode_judp, encode_judp
from ._mapping import Bridge
from ._payloads import (
    ConfirmControl,
    ControlResponse,
    IdentificationType,
    QueryIdentification,
    RejectControl,
    RejectResponse,
    ReleaseControl,
    ReportControl,
    ReportHeartbeatPulse,
    ReportIdentification,
    RequestControl,
    decode_payload,
    encode_payload,
)
from ._reassembly import Reassembler

if TYPE_CHECKING:
    from ups import Message, Node

log = logging.getLogger("ups.jaus")

CONTROL_TIMEOUT = 5.0  #: seconds of silence after which the controlling OCU loses control
_QUERY_OF: dict[int, str] = {  # Query code -> the Report it asks for
    MessageCode.QUERY_GLOBAL_POSE: "ReportGlobalPose",
}


@dataclass
class _Control:
    holder: JausId
    authority: int
    heard: float


class JausHost(asyncio.DatagramProtocol):
    """A JAUS component ``me`` on ``node``, serving JUDP datagrams at ``listen``."""

    def __init__(
        self,
        node: Node,
        bridge: Bridge,
        me: JausId,
        *,
        name: str = "UPS robot",
        authority: int = 0,
        control_timeout: float = CONTROL_TIMEOUT,
    ) -> None:
        self.node = node
        self.bridge = bridge
        self.me = me
        self.name = name
        self.authority = authority  # the lowest authority that may take control
        self.control_timeout = control_timeout
        self.control: _Control | None = None
        self.latest: dict[str, bytes] = {}  # report message -> its channel's latest event
        self.transport: asyncio.DatagramTransport | None = None
        self._sequence = 0
        self._reassembler = Reassembler()
        self.counters = dict.fromkeys(
            ("received", "malformed", "unserved", "commands", "refused_without_control",
             "control_granted", "control_refused", "replies", "not_yet", "handler_errors"), 0,
        )  # fmt: skip

    async def start(self, host: str, port: int) -> tuple[str, int]:
        """Advertise the commands' channels, subscribe to the reports', open the UDP socket;
        returns the address bound."""
        for message, entry in self.bridge.items():
            if entry.command:  # bound now: commands are published from the datagram callback
                await self.node.advertise(entry.channel.channel, max_size=entry.channel.size or 0)
            else:
                await self.node.subscribe(entry.channel.channel, callback=self._keeper(message))
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(lambda: self, local_addr=(host, port))
        self.transport = transport
        bound = transport.get_extra_info("sockname")
        return bound[0], bound[1]

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()

    def stats(self) -> dict[str, int]:
        counts = self._reassembler.counts
        kinds = ("expired", "evicted", "duplicate", "conflicting", "oversized", "mismatched")
        parts = {f"parts_{kind}": getattr(counts, kind) for kind in kinds}
        return {**self.counters, **parts}

    def _keeper(self, message: str) -> Callable[[Message], None]:
        def keep(msg: Message) -> None:
            self.latest[message] = msg.data

        return keep

    # --- receiving ---------------------------------------------------------------------------

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            messages = decode_judp(data)
        except JausDecodeError as exc:
            self.counters["malformed"] += 1
            log.debug("malformed datagram from %s: %s", addr, exc)
            return
        for part in messages:
            message = self._reassembler.feed(part, time.monotonic())
            if message is None:
                continue
            self.counters["received"] += 1
            try:
                self._handle(message, addr)
            except JausDecodeError:
                self.counters["malformed"] += 1
            except Exception:  # one bad message must not stop the component
                self.counters["handler_errors"] += 1
                log.exception("could not handle a JAUS message from %s", addr)

    def _handle(self, message: JudpMessage, addr: tuple[str, int]) -> None:
        code, source = message.code, message.header.source
        if code is None:
            return  # an ACK/NAK response
        payload = decode_payload(code, message.payload)
        self._heard(source)
        if isinstance(payload, RequestControl):
            self._request_control(source, payload.authority, addr)
        elif isinstance(payload, ReleaseControl):
            if self.control is not None and self.control.holder == source:
                self.control = None
            self._reply(addr, source, RejectControl(RejectResponse.CONTROL_RELEASED))
        elif code == MessageCode.QUERY_CONTROL:
            held = self.control
            holder = held.holder if held else JausId(0, 0, 0)
            reply = ReportControl(holder.subsystem, holder.node, holder.component,
                                  held.authority if held else 0)  # fmt: skip
            self._reply(addr, source, reply)
        elif code == MessageCode.QUERY_HEARTBEAT_PULSE:
            self._reply(addr, source, ReportHeartbeatPulse())
        elif isinstance(payload, QueryIdentification):
            self._reply(addr, source, ReportIdentification(
                payload.query_type, IdentificationType.COMPONENT, self.name))  # fmt: skip
        elif payload is not None and type(payload).__name__ in self.bridge:
            self._command(type(payload).__name__, payload, source)
        elif code in _QUERY_OF and _QUERY_OF[code] in self.bridge:
            self._query(_QUERY_OF[code], addr, source)
        else:
            self.counters["unserved"] += 1

    def _heard(self, source: JausId) -> None:
        held = self.control
        if held is None:
            return
        now = time.monotonic()
        if now - held.heard > self.control_timeout:
            log.info("control by %s lapsed", held.holder)
            self.control = None
        elif held.holder == source:
            held.heard = now

    def _request_control(self, source: JausId, authority: int, addr: tuple[str, int]) -> None:
        held = self.control
        if authority < self.authority:
            response = ControlResponse.INSUFFICIENT_AUTHORITY
        elif held is None or held.holder == source or authority > held.authority:
            self.control = _Control(source, authority, time.monotonic())
            response = ControlResponse.CONTROL_ACCEPTED
        else:
            response = ControlResponse.NOT_AVAILABLE
        granted = response == ControlResponse.CONTROL_ACCEPTED
        self.counters["control_granted" if granted else "control_refused"] += 1
        self._reply(addr, source, ConfirmControl(response))

    def _command(self, message: str, payload: Any, source: JausId) -> None:
        entry = self.bridge[message]
        if not entry.command:
            self.counters["unserved"] += 1
            return
        if self.control is None or self.control.holder != source:
            self.counters["refused_without_control"] += 1
            return
        self.counters["commands"] += 1
        self.node.publish_nowait(entry.channel.channel, entry.to_ups(payload))

    def _query(self, message: str, addr: tuple[str, int], source: JausId) -> None:
        data = self.latest.get(message)
        if data is None:
            self.counters["not_yet"] += 1
            return
        self._reply(addr, source, self.bridge[message].from_ups(data))

    # --- sending -----------------------------------------------------------------------------

    def _reply(self, addr: tuple[str, int], to: JausId, payload: Any) -> None:
        code, body = encode_payload(payload)
        header = JudpHeader(destination=to, source=self.me, sequence=self._sequence)
        self._sequence = (self._sequence + 1) & 0xFFFF
        assert self.transport is not None
        self.transport.sendto(encode_judp([JudpMessage(header, code, body)]), addr)
        self.counters["replies"] += 1


__all__ = ["CONTROL_TIMEOUT", "JausHost"]
