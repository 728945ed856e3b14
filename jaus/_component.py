"""What the JAUS component does with a message, whatever framing carried it: the services of
the IGVC interoperability profile, backed by UPS channels through the mapping.

- Transport, Liveness (heartbeat), Discovery (identification, configuration, services).
- AccessControl and Management (``_access.Access``: control, status, emergencies).
- Events (``_events.Events``): periodic and every-change events on any query answered here.
- Mobility, from the mapping: a mapped command (``Set…``) is published on its channel when
  its sender holds control and the component is READY; a mapped report (``Report…``) answers
  its query from the channel's latest event; the query of a mapped command's report (Query
  Wrench Effort…) is answered with the last command carried out.
- The Local Waypoint List Driver and its List Manager (``_waypoint_list``), when Set Local
  Waypoint and Report Local Pose are both mapped.

The host (``_host.JausHost``) owns the socket and the clients; it hands each decoded message to
:meth:`Component.handle` with the client it came from, and this sends answers through the
``send`` callback it was given. Nothing here blocks.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ._access import CONTROL_TIMEOUT, Access, Address, Notes, State
from ._codec import JausDecodeError, JausId
from ._events import EVENT_TIMEOUT, MAX_RATE, EventRefused, Events, Subscription
from ._mapping import Bridge
from ._messages import PAYLOAD_TYPES, decode_payload, encode_payload
from ._messages import payloads as p
from ._waypoint_list import QUERIES as LIST_QUERIES
from ._waypoint_list import SERVICES as LIST_SERVICES
from ._waypoint_list import WaypointList

if TYPE_CHECKING:
    from ups import Message, Node

log = logging.getLogger("ups.jaus")

CORE_SERVICES = (  # (URI, major, minor) of what every component here offers
    ("urn:jaus:jss:core:Transport", 1, 0),
    ("urn:jaus:jss:core:Events", 1, 1),
    ("urn:jaus:jss:core:AccessControl", 1, 1),
    ("urn:jaus:jss:core:Management", 1, 1),
    ("urn:jaus:jss:core:Liveness", 1, 1),
    ("urn:jaus:jss:core:Discovery", 1, 1),
)
MOBILITY_SERVICES = {  # a mobility service is offered when one of its messages is mapped
    "urn:jaus:jss:mobility:PrimitiveDriver": ("SetWrenchEffort",),
    "urn:jaus:jss:mobility:GlobalPoseSensor": ("ReportGlobalPose",),
    "urn:jaus:jss:mobility:LocalPoseSensor": ("ReportLocalPose",),
    "urn:jaus:jss:mobility:VelocityStateSensor": ("ReportVelocityState",),
    "urn:jaus:jss:mobility:LocalWaypointDriver": ("SetLocalWaypoint", "SetTravelSpeed"),
}
_BY_NAME = {cls.__name__: cls for cls in PAYLOAD_TYPES.values()}


class Unserved(Exception):
    """No service of this component answers that message."""


class Component:
    def __init__(
        self,
        node: Node,
        bridge: Bridge,
        me: JausId,
        *,
        send: Callable[[Any, Any], None],
        name: str = "UPS robot",
        minimum_authority: int = 0,
        control_timeout: float = CONTROL_TIMEOUT,
        event_timeout: float = EVENT_TIMEOUT,
        counters: dict[str, int],
    ) -> None:
        self.node, self.bridge, self.me, self.name = node, bridge, me, name
        self._send = send
        self.access = Access(minimum_authority=minimum_authority, timeout=control_timeout)
        self.authority = minimum_authority  # this component's own authority (Set Authority)
        self.latest: dict[str, tuple[bytes, float]] = {}  # report -> its latest event, when
        self.last_command: dict[str, Any] = {}  # mapped command -> the last one carried out
        self.counters = counters
        for key in (
            "commands",
            "refused_without_control",
            "refused_not_ready",
            "refused_in_emergency",
            "control_granted",
            "control_refused",
            "authority_capped",
            "refused_other_address",
            "control_lapsed",
            "unserved",
            "not_yet",
            "replies",
            "pose_errors",
        ):
            counters.setdefault(key, 0)
        self.events = Events(
            report_of=self._report_of,
            answer=self._answer_bytes,
            send=self._send_event,
            cap=self._cap,
            counters=counters,
            timeout=event_timeout,
        )
        self.routes: dict[JausId, Any] = {}  # the latest route of each client heard
        self.notes = Notes(counters, log)  # refusals: counted, and logged now and then
        self.on_shutdown: Callable[[], None] | None = None
        self._handlers: dict[str, Callable[[Any, Any], None]] = {
            "RequestControl": self._request_control,
            "ReleaseControl": self._release_control,
            "SetAuthority": self._set_authority,
            "Resume": self._management,
            "Standby": self._management,
            "Reset": self._management,
            "Shutdown": self._management,
            "SetEmergency": self._emergency,
            "ClearEmergency": self._emergency,
            "CreateEvent": self._create_event,
            "UpdateEvent": self._update_event,
            "CancelEvent": self._cancel_event,
        }
        self.waypoints: WaypointList | None = None  # a list driver needs waypoints and a pose
        if "SetLocalWaypoint" in bridge and "ReportLocalPose" in bridge:
            self.waypoints = WaypointList(
                access=self.access,
                carry_out=self._carry_out,
                reply=self.reply,
                changed=self.events.changed,
                counters=counters,
            )
            self._handlers.update(self.waypoints.handlers)

    async def start(self) -> None:
        """Advertise the mapped commands' channels and subscribe to the mapped reports'."""
        for message, entry in self.bridge.items():
            if entry.command:
                await self.node.advertise(entry.channel.channel, max_size=entry.channel.size or 0)
            else:
                await self.node.subscribe(entry.channel.channel, callback=self._keeper(message))

    def close(self) -> None:
        self.events.close()

    def services(self) -> list[tuple[str, int, int]]:
        mobility = [
            (uri, 1, 0)
            for uri, messages in MOBILITY_SERVICES.items()
            if any(m in self.bridge for m in messages)
        ]
        return [*CORE_SERVICES, *mobility, *(LIST_SERVICES if self.waypoints else ())]

    # --- receiving -------------------------------------------------------------------------

    def handle(self, client: Any, source: JausId, payload: Any) -> None:
        """One decoded message from ``source``, reached through ``client``."""
        now = time.monotonic()
        self.routes[source] = client
        self.access.heard_from(source, now)
        self.events.heard_from(source, now)
        name = type(payload).__name__
        handler = self._handlers.get(name)
        if handler is not None:
            handler(source, payload)
        elif name in self.bridge and self.bridge[name].command:
            self._command(source, name, payload)
        else:
            try:
                report = self.answer(payload)
            except Unserved:
                self.counters["unserved"] += 1
                return
            if report is None:
                self.counters["not_yet"] += 1  # JAUS has no "no data" reply: nothing is sent
            else:
                self.reply(source, report)

    def tick(self, now: float) -> None:
        """Housekeeping, about once a second: lapsed control, silent clients' events."""
        lapsed = self.access.expire(now)
        if lapsed is not None:
            self.counters["control_lapsed"] += 1
            log.info("control by %s lapsed after %.0f s of silence", lapsed, self.access.timeout)
            self.reply(lapsed, p.RejectControl(p.RejectResponse.CONTROL_RELEASED))
        for sub in self.events.expire(now):
            log.info("event %d of %s cancelled: its client went silent", sub.event_id, sub.owner)

    def forget(self, source: JausId) -> None:
        """The host dropped this client: its events go with it."""
        self.routes.pop(source, None)
        self.events.drop_owner(source)

    # --- answers ---------------------------------------------------------------------------

    def answer(self, query: Any) -> Any | None:
        """The report answering ``query``, None when its data has not arrived yet;
        :class:`Unserved` when nothing here answers it."""
        name = type(query).__name__
        topic = name.removeprefix("Query")
        report = f"Report{topic}"
        entry = self.bridge.get(report)
        if entry is not None and not entry.command:  # the mapping first: the robot's data
            latest = self.latest.get(report)
            return None if latest is None else _narrow(entry.from_ups(*latest), query)
        fixed = self._fixed_answer(name, query)
        if fixed is not None:
            return fixed
        if name == topic or report not in _BY_NAME:
            raise Unserved(name)
        setter = f"Set{topic}"
        if setter in self.bridge:
            last = self.last_command.get(setter)
            if last is None:
                return None
            values = {f.name: getattr(last, f.name) for f in dataclasses.fields(last)}
            return _narrow(_BY_NAME[report](**values), query)
        raise Unserved(name)

    def _fixed_answer(self, name: str, query: Any) -> Any | None:
        access = self.access
        if name == "QueryControl":
            holder = access.holder or JausId(0, 0, 0)
            return p.ReportControl(
                holder.subsystem, holder.node, holder.component, access.authority
            )
        if name == "QueryAuthority":
            return p.ReportAuthority(self.authority)
        if name == "QueryStatus":
            return p.ReportStatus(p.ManagementStatus(int(access.state)))
        if name == "QueryTimeout":
            return p.ReportTimeout(min(255, round(access.timeout)))
        if name == "QueryHeartbeatPulse":
            return p.ReportHeartbeatPulse()
        if name == "QueryIdentification":
            return p.ReportIdentification(
                query.query_type, p.IdentificationType.COMPONENT, self.name
            )
        if name == "QueryConfiguration":
            me = p.ComponentEntry(self.me.component, 1)
            return p.ReportConfiguration((p.NodeEntry(self.me.node, (me,)),))
        if name == "QueryServices":
            offered = tuple(p.Service(uri, major, minor) for uri, major, minor in self.services())
            me = p.ComponentEntry(self.me.component, 1, offered)
            return p.ReportServices((p.NodeEntry(self.me.node, (me,)),))
        if name in LIST_QUERIES and self.waypoints is not None:
            return self.waypoints.answer(name, query)
        if name == "QueryEventTimeout":
            return p.ReportEventTimeout(max(1, round(self.events.timeout / 60)))
        return None

    def _report_of(self, query: bytes) -> str | None:
        try:
            payload = _decode_message(query)
            self.answer(payload)
        except (JausDecodeError, Unserved):
            return None
        return type(payload).__name__.replace("Query", "Report", 1)

    def _answer_bytes(self, query: bytes) -> Any | None:
        return self.answer(_decode_message(query))

    def _cap(self, report: str) -> float:
        entry = self.bridge.get(report)
        return entry.rate if entry is not None and entry.rate else MAX_RATE

    # --- AccessControl and Management ------------------------------------------------------

    def _request_control(self, source: JausId, msg: Any) -> None:
        address = self.routes[source].addr
        authority = self._capped(source, address, msg.authority)
        if authority is None:  # its address is in no range of the mapping's [authority]
            response, displaced = p.ControlResponse.INSUFFICIENT_AUTHORITY, None
        else:
            response, displaced = self.access.request(source, authority, time.monotonic(), address)
        granted = response == p.ControlResponse.CONTROL_ACCEPTED
        self.counters["control_granted" if granted else "control_refused"] += 1
        if displaced is not None:
            self.reply(displaced, p.RejectControl(p.RejectResponse.CONTROL_RELEASED))
        self.reply(source, p.ConfirmControl(response))

    def _capped(self, source: JausId, address: Address, asked: int) -> int | None:
        """The authority granted to ``source`` at ``address`` asking for ``asked``: at most
        its address range's cap in the mapping (None: no control at all)."""
        caps = self.bridge.authority
        if caps is None:
            return asked
        found = caps.cap(str(address[0]))
        if found is not None and found[1] >= asked:
            return asked
        if found is None:
            granted, why = None, "in no [authority] range: no control"
        else:
            granted, why = found[1], f"capped to {found[1]} ({found[0]})"
        self.notes("authority_capped", "Request Control from %s at %s: authority %d %s",
                   source, _shown(address), asked, why)  # fmt: skip
        return granted

    def _release_control(self, source: JausId, msg: Any) -> None:
        released = self.access.release(source)
        self.reply(
            source,
            p.RejectControl(
                p.RejectResponse.CONTROL_RELEASED if released else p.RejectResponse.NOT_AVAILABLE
            ),
        )

    def _set_authority(self, source: JausId, msg: Any) -> None:
        if not self.access.controls(source):
            self.counters["refused_without_control"] += 1
        elif msg.authority >= self.access.minimum_authority:
            self.authority = msg.authority
            self._publish_if_mapped("SetAuthority", msg)

    def _management(self, source: JausId, msg: Any) -> None:
        name = type(msg).__name__
        done = getattr(self.access, name.lower())(source)
        if not done:
            self.counters[
                "refused_without_control"
                if not self.access.controls(source)
                else "refused_not_ready"
            ] += 1
            return
        self._publish_if_mapped(name, msg)
        if name in ("Reset", "Shutdown"):
            self.reply(source, p.RejectControl(p.RejectResponse.CONTROL_RELEASED))
        if self.access.state == State.SHUTDOWN and self.on_shutdown is not None:
            self.on_shutdown()

    def _emergency(self, source: JausId, msg: Any) -> None:
        self.emergency(source, self.routes[source].addr, msg)

    def emergency(self, source: JausId, address: Address, msg: Any) -> None:
        """Set or Clear Emergency from ``source`` at ``address``. The host calls it for a Set
        Emergency it refuses otherwise (the holder's id from elsewhere): a stop is taken from
        anyone."""
        name = type(msg).__name__
        done = (
            self.access.set_emergency(source, address)
            if name == "SetEmergency"
            else self.access.clear_emergency(source, address)
        )
        if not done:
            self.counters["refused_emergency"] = self.counters.get("refused_emergency", 0) + 1
            return
        self._publish_if_mapped(name, msg)

    # --- mobility commands -----------------------------------------------------------------

    def _command(self, source: JausId, name: str, msg: Any) -> None:
        refusal = self.access.refusal(source)
        if refusal is not None:
            self.counters[refusal] += 1
            return
        self.counters["commands"] += 1
        self._carry_out(name, msg)

    def _carry_out(self, name: str, msg: Any) -> None:
        """A command in force: published on its channel when mapped, and remembered."""
        self.last_command[name] = msg
        self._publish_if_mapped(name, msg)

    def _publish_if_mapped(self, name: str, msg: Any) -> None:
        entry = self.bridge.get(name)
        if entry is not None and entry.command:
            self.node.publish_nowait(entry.channel.channel, entry.to_ups(msg))

    def _keeper(self, report: str) -> Callable[[Message], None]:
        def keep(msg: Message) -> None:
            self.latest[report] = (msg.data, msg.timestamp)
            self.events.changed(report)

        waypoints = self.waypoints
        if report != "ReportLocalPose" or waypoints is None:
            return keep
        pose = self.bridge[report]

        def keep_and_drive(msg: Message) -> None:  # the robot's pose also drives the list
            keep(msg)
            try:
                waypoints.moved(pose.from_ups(msg.data))
            except Exception:  # a pose that cannot be read drives nowhere
                self.counters["pose_errors"] += 1
                log.exception("local pose %s: not readable", msg.data.hex())

        return keep_and_drive

    # --- Events ----------------------------------------------------------------------------

    def _create_event(self, source: JausId, msg: Any) -> None:
        try:
            sub = self.events.create(
                source,
                self.routes[source],
                msg.request_id,
                int(msg.event_type),
                msg.requested_periodic_rate,
                msg.query_message,
            )
        except EventRefused as refused:
            self.reply(source, p.RejectEventRequest(msg.request_id, p.EventRejection(refused.code)))
            return
        self.reply(source, p.ConfirmEventRequest(msg.request_id, sub.event_id, sub.rate))

    def _update_event(self, source: JausId, msg: Any) -> None:
        try:
            sub = self.events.update(
                source,
                self.routes[source],
                msg.request_id,
                int(msg.event_type),
                msg.requested_periodic_rate,
                msg.event_id,
                msg.query_message,
            )
        except EventRefused as refused:
            self.reply(source, p.RejectEventRequest(msg.request_id, p.EventRejection(refused.code)))
            return
        self.reply(source, p.ConfirmEventRequest(msg.request_id, sub.event_id, sub.rate))

    def _cancel_event(self, source: JausId, msg: Any) -> None:
        try:
            sub = self.events.cancel(source, msg.event_id)
        except EventRefused as refused:
            self.reply(source, p.RejectEventRequest(msg.request_id, p.EventRejection(refused.code)))
            return
        self.reply(source, p.ConfirmEventRequest(msg.request_id, sub.event_id, sub.rate))

    def _send_event(self, sub: Subscription, report: Any) -> None:
        code, body = encode_payload(report)
        message = code.to_bytes(2, "little") + body
        self._send(sub.route, p.Event(sub.event_id, sub.sequence, message))

    # --- sending ---------------------------------------------------------------------------

    def reply(self, to: JausId, payload: Any) -> None:
        route = self.routes.get(to)
        if route is None:
            return  # a client the host has forgotten
        self._send(route, payload)
        self.counters["replies"] += 1

    def status(self) -> dict[str, Any]:
        holder = self.access.holder
        return {
            "state": self.access.state.name,
            "controller": str(holder) if holder else None,
            "authority": self.access.authority,
            **({"waypoint_list": self.waypoints.status()} if self.waypoints else {}),
            "events": [
                {
                    "event": s.event_id,
                    "client": str(s.owner),
                    "kind": s.kind,
                    "rate": s.rate,
                    "report": s.report,
                }
                for s in self.events.table.values()
            ],
        }


def _shown(address: Address) -> str:
    """``HOST:PORT`` of a UDP address."""
    return f"{address[0]}:{address[1]}" if len(address) >= 2 else str(address)


def _decode_message(message: bytes) -> Any:
    """A whole message (code u16 LE, then payload), as Create Event carries a query."""
    if len(message) < 2:
        raise JausDecodeError("a message is at least its 2-byte code")
    payload = decode_payload(int.from_bytes(message[:2], "little"), message[2:])
    if payload is None:
        raise JausDecodeError("a query this component does not know")
    return payload


def _narrow(report: Any, query: Any) -> Any:
    """Only the fields the query's presence vector asks for (bit i: the i-th optional field,
    ``PV_FIELDS`` where a record has fields that are always present)."""
    wanted = getattr(query, "presence_vector", None)
    if wanted is None:
        return report
    optional = getattr(report, "PV_FIELDS", None) or [f.name for f in dataclasses.fields(report)]
    return dataclasses.replace(
        report, **{name: None for i, name in enumerate(optional) if not wanted >> i & 1}
    )


__all__ = ["Component", "Unserved"]
