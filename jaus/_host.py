"""``ups jaus``: a JAUS component on a UPS node, answering JUDP and RA 3.3 datagrams.

The host owns the UDP socket and the table of clients (operator control units); what the
component does with a message is ``_component.Component``'s. Each datagram is recognised by
its first bytes: ``JAUS01.0`` is the RA 3.3 framing of paper 001, a first byte 2 is JUDP
(AS5669A). A client is answered in the framing it spoke last.

Messages are served when addressed to this component or broadcast (a part of the
destination 0xFFFF/0xFF in JUDP, 0xFF in RA 3.3); others are counted (``not_for_me``). In RA
3.3, where each service is a component of its own with a fixed id (``RA33_COMPONENTS``: paper
001's OCU asks the Global Pose Sensor, component 38), a message to the id of a service this
component offers, on its subsystem and node, is served too, and answered from that id.

Bounds, each counted when it bites:

- ``MAX_CLIENTS`` clients known at once; a new one evicts the one silent longest, never the
  controlling one (``clients_evicted``), and with it its events. A client silent for
  ``CLIENT_TIMEOUT`` seconds is forgotten (``clients_gone``).
- large JUDP messages go through a bounded ``Reassembler`` (its drops counted by reason);
  RA 3.3 multi-packet messages are not served (``unserved``).
- a message asking for an acknowledgement (ACK/NAK 1) is answered with an ACK carrying its
  sequence number (and, in RA 3.3, its command code), after it was handled (``acks``);
- datagrams that do not decode (``malformed``) and messages no service here answers
  (``unserved``) are counted and dropped; an exception inside a service is logged and counted
  (``handler_errors``) and the component keeps serving.
- while a client holds control, its JAUS id is bound to its UDP address: a message with that
  id from another address never reaches the holder's state (its client, its route, its events,
  its control's liveness). A query is answered, to the address it came from, as any client's
  is (what anyone may read); a Set Emergency is taken (anyone may stop the robot); anything
  else is dropped, counted (``refused_other_address``) and logged (``_access.Notes``), and
  told so when JAUS has a word for it: Request and Release Control are answered Not Available,
  an event request Reject Event Request (connection refused, saying why). The parts of a
  large message are never joined with the holder's.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from ._codec import AckNak, JausDecodeError, JausId
from ._component import Component, Unserved
from ._event_payloads import (
    CancelEvent,
    CreateEvent,
    EventRejection,
    RejectEventRequest,
    UpdateEvent,
)
from ._events import EVENT_TIMEOUT
from ._judp import (
    Broadcast,
    DataFlags,
    JudpHeader,
    JudpMessage,
    decode_judp,
    encode_judp,
    split_message,
)
from ._management_payloads import SetEmergency
from ._mapping import Bridge
from ._messages import decode_payload, encode_payload
from ._payloads import (
    ConfirmControl,
    ControlResponse,
    RejectControl,
    RejectResponse,
    ReleaseControl,
    RequestControl,
)
from ._ra33 import (
    RA33_PREFIX,
    Ra33Address,
    Ra33DataFlags,
    Ra33Header,
    Ra33Message,
    decode_ra33,
    encode_ra33,
)
from ._ra33_payloads import decode_ra33_payload, encode_ra33_payload
from ._reassembly import Reassembler

if TYPE_CHECKING:
    from ups import Node

log = logging.getLogger("ups.jaus")

MAX_CLIENTS = 64  #: clients (OCUs) known at once
#: RA 3.3's component ids of the mobility services offered here (OpenJAUS's jausComponent.h,
#: "pre-defined Jaus Component Ids according to RA 3.2"; paper 001 names 33 and 38)
RA33_COMPONENTS = {
    "urn:jaus:jss:mobility:PrimitiveDriver": 33,
    "urn:jaus:jss:mobility:GlobalPoseSensor": 38,
    "urn:jaus:jss:mobility:LocalPoseSensor": 41,
    "urn:jaus:jss:mobility:VelocityStateSensor": 42,
    "urn:jaus:jss:mobility:LocalWaypointDriver": 46,
}
CLIENT_TIMEOUT = EVENT_TIMEOUT  #: seconds of silence after which a client is forgotten
TICK = 0.5  #: seconds between housekeeping passes (control timeout, silent clients)


@dataclass(slots=True)
class Client:
    """An operator control unit as the host knows it."""

    id: JausId
    addr: tuple[str, int]
    ra33: bool  #: it spoke the RA 3.3 framing last
    instance: int  #: its RA 3.3 instance
    heard: float
    messages: int = 0
    ra33_as: int = 0  #: the RA 3.3 component id it spoke to last (answers come from it)


class JausHost(asyncio.DatagramProtocol):
    """A JAUS component ``me`` on ``node``, serving the datagrams that reach its socket."""

    def __init__(
        self,
        node: Node,
        bridge: Bridge,
        me: JausId,
        *,
        name: str = "UPS robot",
        authority: int = 0,
        control_timeout: float | None = None,
        max_clients: int = MAX_CLIENTS,
    ) -> None:
        self.me = me
        self.counters = dict.fromkeys(
            (
                "datagrams",
                "received",
                "malformed",
                "not_for_me",
                "handler_errors",
                "clients_evicted",
                "clients_gone",
                "sent",
                "acks",
            ),
            0,
        )
        extra = {} if control_timeout is None else {"control_timeout": control_timeout}
        self.component = Component(
            node,
            bridge,
            me,
            send=self._send,
            name=name,
            minimum_authority=authority,
            counters=self.counters,
            **extra,
        )
        self.clients: dict[JausId, Client] = {}
        self.max_clients = max_clients
        self.transport: asyncio.DatagramTransport | None = None
        self.finished = asyncio.Event()  # set by Shutdown from the controlling client
        self.component.on_shutdown = self.finished.set
        self._sequence = 0
        self._reassembler = Reassembler()
        self._ticker: asyncio.TimerHandle | None = None
        self.ra33_ids = {me.component} | {  # the RA 3.3 ids served: its own, its services'
            RA33_COMPONENTS[uri]
            for uri, _, _ in self.component.services()
            if uri in RA33_COMPONENTS
        }

    async def start(self, host: str, port: int) -> tuple[str, int]:
        """Bind the mapped channels, open the UDP socket; returns the address bound."""
        await self.component.start()
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: self, local_addr=(host, port), allow_broadcast=True
        )
        self.transport = transport
        self._ticker = loop.call_later(TICK, self._tick)
        bound = transport.get_extra_info("sockname")
        return bound[0], bound[1]

    def close(self) -> None:
        if self._ticker is not None:
            self._ticker.cancel()
        self.component.close()
        if self.transport is not None:
            self.transport.close()

    def stats(self) -> dict[str, int]:
        counts = self._reassembler.counts
        kinds = ("expired", "evicted", "duplicate", "conflicting", "oversized", "mismatched")
        parts = {f"parts_{kind}": getattr(counts, kind) for kind in kinds}
        return {
            **self.counters,
            **parts,
            "clients": len(self.clients),
            "events": len(self.component.events.table),
        }

    def status(self) -> dict[str, Any]:
        """The component, its clients and counters (``ups status`` shows it as ``jaus``)."""
        now = time.monotonic()
        return {
            "jaus": {
                "id": str(self.me),
                **self.component.status(),
                "clients": [
                    {
                        "id": str(c.id),
                        "address": f"{c.addr[0]}:{c.addr[1]}",
                        "framing": "RA 3.3" if c.ra33 else "JUDP",
                        "messages": c.messages,
                        "silent_s": round(now - c.heard, 1),
                    }
                    for c in self.clients.values()
                ],
                "stats": self.stats(),
            }
        }

    # --- receiving -------------------------------------------------------------------------

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.counters["datagrams"] += 1
        try:
            if data.startswith(RA33_PREFIX):
                self._ra33(data, addr)
            else:
                self._judp(data, addr)
        except JausDecodeError as exc:
            self.counters["malformed"] += 1
            log.debug("malformed datagram from %s: %s", addr, exc)

    def _judp(self, data: bytes, addr: tuple[str, int]) -> None:
        for part in decode_judp(data):
            h = part.header
            if not _for(self.me, h.destination, 0xFFFF):
                self.counters["not_for_me"] += 1
                continue
            if h.data_flags != DataFlags.SINGLE and not self.component.access.admits(
                h.source, addr
            ):  # a part with the controller's id from elsewhere: never mixed with its parts
                self._refuse(h.source, addr)
            else:
                message = self._reassembler.feed(part, time.monotonic())
                if message is not None and message.code is not None:  # else held, or an ACK
                    self._serve(
                        h.source,
                        addr,
                        False,
                        1,
                        lambda m=message: decode_payload(m.code, m.payload),
                    )
            if h.ack_nak == AckNak.REQUEST:
                ack = replace(
                    h,
                    destination=h.source,
                    source=self.me,
                    ack_nak=AckNak.ACK,
                    data_flags=DataFlags.SINGLE,
                    broadcast=Broadcast.NONE,
                )
                self._sendto(encode_judp([JudpMessage(ack, None)]), addr)
                self.counters["acks"] += 1

    def _ra33(self, data: bytes, addr: tuple[str, int]) -> None:
        message = decode_ra33(data)
        h = message.header
        to = h.destination
        as_id = self.me.component if to.component == 0xFF else to.component  # answered as
        here = JausId(to.subsystem, to.node, self.me.component)
        if as_id not in self.ra33_ids or not _for(self.me, here, 0xFF):
            self.counters["not_for_me"] += 1
            return
        src = h.source
        source = JausId(src.subsystem, src.node, src.component)
        if h.data_flags != Ra33DataFlags.SINGLE:
            self.counters["unserved"] += 1  # RA 3.3 multi-packet messages: not served
            return
        self._serve(
            source,
            addr,
            True,
            src.instance,
            lambda: decode_ra33_payload(h.command_code, message.data),
            as_id,
        )
        if h.ack_nak == AckNak.REQUEST:
            ack = replace(
                h,
                destination=h.source,
                source=Ra33Address(self.me.subsystem, self.me.node, as_id),
                ack_nak=AckNak.ACK,
            )
            self._sendto(encode_ra33(Ra33Message(ack)), addr)
            self.counters["acks"] += 1

    def _serve(
        self,
        source: JausId,
        addr: tuple[str, int],
        ra33: bool,
        instance: int,
        decode: Any,
        ra33_as: int = 0,
    ) -> None:
        try:
            payload = decode()
        except JausDecodeError as exc:
            self.counters["malformed"] += 1
            log.debug("malformed message from %s: %s", addr, exc)
            return
        self.counters["received"] += 1
        if not self.component.access.admits(source, addr):
            to = Client(source, addr, ra33, instance, 0.0, ra33_as=ra33_as or self.me.component)
            try:
                self._refuse(source, addr, payload, to)
            except Exception:  # one bad message must not stop the component
                self.counters["handler_errors"] += 1
                log.exception("could not answer %s from %s", type(payload).__name__, addr)
            return
        client = self._client(source, addr, ra33, instance)
        client.ra33_as = ra33_as or self.me.component
        if payload is None:
            self.component.counters["unserved"] += 1
            return
        try:
            self.component.handle(client, source, payload)
        except Exception:  # one bad message must not stop the component
            self.counters["handler_errors"] += 1
            log.exception("could not handle %s from %s", type(payload).__name__, source)

    def _refuse(
        self, source: JausId, addr: tuple[str, int], payload: Any = None, to: Client | None = None
    ) -> None:
        """A message with the controller's id from another address (``to`` reaches it there):
        a query is answered, a Set Emergency taken; the rest is refused, counted, logged, and
        told so where JAUS can say it."""
        if isinstance(payload, SetEmergency):
            self.component.emergency(source, addr, payload)
            return
        if to is not None and _is_query(payload):
            self._answer_elsewhere(to, payload)
            return
        holder = self.component.access.holder_address or ("?", 0)
        self.component.notes(
            "refused_other_address",
            "%s from %s:%d refused: %s controls the component from another address, %s:%d",
            type(payload).__name__ if payload is not None else "a message",
            addr[0], addr[1], source, holder[0], holder[1],
        )  # fmt: skip
        if to is None:
            return
        if isinstance(payload, RequestControl):
            self._send(to, ConfirmControl(ControlResponse.NOT_AVAILABLE))
        elif isinstance(payload, ReleaseControl):
            self._send(to, RejectControl(RejectResponse.NOT_AVAILABLE))
        elif isinstance(payload, CreateEvent | UpdateEvent | CancelEvent):
            why = f"{source} controls this component from another address"
            refused = EventRejection.CONNECTION_REFUSED
            self._send(to, RejectEventRequest(payload.request_id, refused, why))

    def _answer_elsewhere(self, to: Client, query: Any) -> None:
        """A query from the controller's id at another address, answered there; nothing about
        the controller (its route, its liveness) changes."""
        try:
            report = self.component.answer(query)
        except Unserved:
            self.counters["unserved"] += 1
            return
        if report is None:
            self.counters["not_yet"] += 1  # JAUS has no "no data" reply: nothing is sent
            return
        self._send(to, report)
        self.counters["replies"] += 1

    def _client(self, source: JausId, addr: tuple[str, int], ra33: bool, instance: int) -> Client:
        now = time.monotonic()
        client = self.clients.get(source)
        if client is None:
            if len(self.clients) >= self.max_clients:
                self._evict()
            client = self.clients[source] = Client(source, addr, ra33, instance, now)
        client.addr, client.ra33, client.instance, client.heard = addr, ra33, instance, now
        client.messages += 1
        return client

    def _evict(self) -> None:
        holder = self.component.access.holder
        candidates = [c for c in self.clients.values() if c.id != holder]
        if candidates:
            oldest = min(candidates, key=lambda c: c.heard)
            self._forget(oldest)
            self.counters["clients_evicted"] += 1

    def _forget(self, client: Client) -> None:
        del self.clients[client.id]
        self.component.forget(client.id)

    def _tick(self) -> None:
        now = time.monotonic()
        try:
            self.component.tick(now)
            holder = self.component.access.holder
            for client in [c for c in self.clients.values() if now - c.heard > CLIENT_TIMEOUT]:
                if client.id != holder:
                    self._forget(client)
                    self.counters["clients_gone"] += 1
        except Exception:
            self.counters["handler_errors"] += 1
            log.exception("JAUS housekeeping failed")
        self._ticker = asyncio.get_running_loop().call_later(TICK, self._tick)

    # --- sending ---------------------------------------------------------------------------

    def _send(self, client: Client, payload: Any) -> None:
        if client.ra33:
            code, body = encode_ra33_payload(payload)
            me = Ra33Address(self.me.subsystem, self.me.node, client.ra33_as or self.me.component)
            to = Ra33Address(
                client.id.subsystem, client.id.node, client.id.component, client.instance
            )
            ra_header = Ra33Header(code, to, me, sequence=self._next(1))
            datagrams = [encode_ra33(Ra33Message(ra_header, body))]
        else:
            code, body = encode_payload(payload)
            header = JudpHeader(destination=client.id, source=self.me, sequence=self._sequence)
            parts = split_message(header, code, body)  # a large message: one part per datagram
            self._next(len(parts))
            datagrams = [encode_judp([part]) for part in parts]
        for datagram in datagrams:
            self._sendto(datagram, client.addr)
        self.counters["sent"] += 1

    def _sendto(self, datagram: bytes, addr: tuple[str, int]) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.sendto(datagram, addr)

    def _next(self, count: int) -> int:
        sequence = self._sequence
        self._sequence = (sequence + count) & 0xFFFF
        return sequence


def _is_query(payload: Any) -> bool:
    """Whether ``payload`` is a query (codes 0x2000-0x3FFF): it asks, it changes nothing."""
    return 0x2000 <= getattr(payload, "CODE", 0) < 0x4000


def _for(me: JausId, to: JausId, broadcast_subsystem: int) -> bool:
    """Whether a message sent to ``to`` is for ``me`` (each part equal or broadcast)."""
    return (
        to.subsystem in (me.subsystem, broadcast_subsystem)
        and to.node in (me.node, 0xFF)
        and to.component in (me.component, 0xFF)
    )


__all__ = ["CLIENT_TIMEOUT", "MAX_CLIENTS", "RA33_COMPONENTS", "Client", "JausHost"]
