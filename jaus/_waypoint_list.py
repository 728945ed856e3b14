"""The Local Waypoint List Driver (AS6009 mobility) on a UPS robot: the List Manager's list of
waypoints (AS5710A core), Execute List, and driving through the list.

The list holds Set Local Waypoint messages, each an element linked to the one before and the
one after it. Set Element inserts after the element its ``previous`` names (at the head for
0) or gives an element in place a new waypoint; the whole request is checked before anything
changes, and it is confirmed, or rejected with the reason, as one. Execute List makes an
element active (the head unless it names one): its waypoint is published on the channel the
mapping gives Set Local Waypoint, and the speed on Set Travel Speed's when that is mapped. Each
local pose the robot reports (the mapping's Report Local Pose channel) within the active
waypoint's tolerance (its own, else ``DEFAULT_TOLERANCE``) makes the next element active and
publishes its waypoint, until the tail is reached; while the component is not READY
(standby, emergency, control lost) the list waits where it is.

Set Element and Delete Element need control; Execute List needs control and a READY component,
as every command; refusals are counted as theirs are. Bounds: ``MAX_ELEMENTS`` in the list
(``elements_refused``, answered with Reject Element Request, out of memory).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from ._access import Access, State
from ._codec import JausDecodeError, JausId
from ._lists import (
    ALL_ELEMENTS,
    JAUS_MESSAGE,
    NO_ELEMENT,
    ConfirmElementRequest,
    DeleteElement,
    Element,
    ElementRejection,
    ExecuteList,
    RejectElementRequest,
    ReportActiveElement,
    ReportElement,
    ReportElementCount,
    ReportElementList,
    SetElement,
)
from ._messages import decode_payload
from ._mobility import ReportLocalPose, SetLocalWaypoint, SetTravelSpeed

MAX_ELEMENTS = 256  #: waypoints in the list at most
DEFAULT_TOLERANCE = 1.0  #: metres: a waypoint without its own tolerance is reached this close
SERVICES = (("urn:jaus:jss:mobility:ListManager", 1, 0),
            ("urn:jaus:jss:mobility:LocalWaypointListDriver", 1, 0))  # fmt: skip
QUERIES = ("QueryElement", "QueryElementList", "QueryElementCount", "QueryActiveElement")


class _Rejected(Exception):
    def __init__(self, code: ElementRejection) -> None:
        self.code = code


class WaypointList:
    def __init__(
        self,
        *,
        access: Access,
        carry_out: Callable[[str, Any], None],
        reply: Callable[[JausId, Any], None],
        changed: Callable[[str], None],
        counters: dict[str, int],
        max_elements: int = MAX_ELEMENTS,
    ) -> None:
        self.access, self._carry_out, self._reply, self._changed = access, carry_out, reply, changed
        self.counters = counters
        for key in ("list_changes", "list_rejected", "elements_refused", "lists_executed",
                    "list_not_executed", "waypoints_reached", "lists_completed"):  # fmt: skip
            counters.setdefault(key, 0)
        self.max_elements = max_elements
        self.order: list[int] = []  # the element UIDs, head to tail
        self.waypoints: dict[int, SetLocalWaypoint] = {}
        self.active = NO_ELEMENT
        self.handlers: dict[str, Callable[[JausId, Any], None]] = {
            "SetElement": self._set,
            "DeleteElement": self._delete,
            "ExecuteList": self._execute,
        }

    # --- the List Manager ------------------------------------------------------------------

    def _set(self, source: JausId, msg: SetElement) -> None:
        if not self.access.controls(source):
            self.counters["refused_without_control"] += 1
            return
        try:
            self.order, self.waypoints = self._inserted(msg.elements)
        except _Rejected as rejected:
            self.counters["list_rejected"] += 1
            self._reply(source, RejectElementRequest(msg.request_id, rejected.code))
            return
        self.counters["list_changes"] += 1
        self._reply(source, ConfirmElementRequest(msg.request_id))

    def _inserted(
        self, elements: tuple[Element, ...]
    ) -> tuple[list[int], dict[int, SetLocalWaypoint]]:
        """The list with ``elements`` set, or :class:`_Rejected`; the list itself unchanged."""
        order, waypoints = list(self.order), dict(self.waypoints)
        uids = [e.uid for e in elements]
        if len(set(uids)) != len(uids):
            raise _Rejected(ElementRejection.INVALID_ELEMENT_ID)
        for e in elements:
            if e.uid in (NO_ELEMENT, ALL_ELEMENTS):
                raise _Rejected(ElementRejection.INVALID_ELEMENT_ID)
            waypoint = _waypoint(e)
            if e.uid in waypoints:  # a new waypoint for an element in place
                at = order.index(e.uid)
                if e.previous != (order[at - 1] if at else NO_ELEMENT):
                    raise _Rejected(ElementRejection.INVALID_PREVIOUS_ELEMENT)
            elif e.previous != NO_ELEMENT and e.previous not in waypoints:
                raise _Rejected(ElementRejection.INVALID_PREVIOUS_ELEMENT)
            elif len(order) >= self.max_elements:
                self.counters["elements_refused"] += 1
                raise _Rejected(ElementRejection.OUT_OF_MEMORY)
            else:
                order.insert(order.index(e.previous) + 1 if e.previous else 0, e.uid)
            waypoints[e.uid] = waypoint
        for e in elements:  # each names what now follows it
            at = order.index(e.uid)
            if e.next != (order[at + 1] if at + 1 < len(order) else NO_ELEMENT):
                raise _Rejected(ElementRejection.INVALID_NEXT_ELEMENT)
        return order, waypoints

    def _delete(self, source: JausId, msg: DeleteElement) -> None:
        if not self.access.controls(source):
            self.counters["refused_without_control"] += 1
            return
        gone = set(self.order) if ALL_ELEMENTS in msg.uids else set(msg.uids)
        if not gone <= set(self.order):
            self.counters["list_rejected"] += 1
            self._reply(
                source, RejectElementRequest(msg.request_id, ElementRejection.ELEMENT_NOT_FOUND)
            )
            return
        self.order = [uid for uid in self.order if uid not in gone]
        self.waypoints = {uid: wp for uid, wp in self.waypoints.items() if uid not in gone}
        if self.active in gone:
            self._activate(NO_ELEMENT)  # what was being driven to is gone: the robot stops here
        self.counters["list_changes"] += 1
        self._reply(source, ConfirmElementRequest(msg.request_id))

    def answer(self, name: str, query: Any) -> Any | None:
        """The report answering a list query (None: no such element)."""
        if name == "QueryElementList":
            return ReportElementList(tuple(self.order))
        if name == "QueryElementCount":
            return ReportElementCount(len(self.order))
        if name == "QueryActiveElement":
            return ReportActiveElement(self.active)
        uid = query.uid
        if uid not in self.waypoints:
            return None
        at = self.order.index(uid)
        before = self.order[at - 1] if at else NO_ELEMENT
        after = self.order[at + 1] if at + 1 < len(self.order) else NO_ELEMENT
        data = SetLocalWaypoint.CODE.to_bytes(2, "little") + self.waypoints[uid].to_bytes()
        return ReportElement(Element(uid, before, after, data))

    # --- driving ---------------------------------------------------------------------------

    def _execute(self, source: JausId, msg: ExecuteList) -> None:
        refusal = self.access.refusal(source)
        if refusal is not None:
            self.counters[refusal] += 1
            return
        start = self.order[0] if msg.start is None and self.order else msg.start
        if start not in self.waypoints:
            self.counters["list_not_executed"] += 1  # an empty list, or no such element
            return
        self.counters["lists_executed"] += 1
        self._carry_out("SetTravelSpeed", SetTravelSpeed(msg.speed))
        self._activate(start)

    def moved(self, pose: ReportLocalPose) -> None:
        """The robot's latest local pose: is the active waypoint reached?"""
        waypoint = self.waypoints.get(self.active)
        if waypoint is None or pose.x is None or pose.y is None:
            return
        if self.access.state != State.READY:  # standby, emergency: the list waits
            return
        tolerance = waypoint.waypoint_tolerance or DEFAULT_TOLERANCE
        if math.hypot(pose.x - waypoint.x, pose.y - waypoint.y) > tolerance:
            return
        self.counters["waypoints_reached"] += 1
        at = self.order.index(self.active)
        if at + 1 < len(self.order):
            self._activate(self.order[at + 1])
        else:
            self.counters["lists_completed"] += 1
            self._activate(NO_ELEMENT)

    def _activate(self, uid: int) -> None:
        self.active = uid
        if uid != NO_ELEMENT:
            self._carry_out("SetLocalWaypoint", self.waypoints[uid])
        self._changed("ReportActiveElement")

    def status(self) -> dict[str, Any]:
        return {"elements": len(self.order), "active": self.active}


def _waypoint(element: Element) -> SetLocalWaypoint:
    """The Set Local Waypoint an element carries; :class:`_Rejected` for anything else."""
    data = element.data
    if element.format != JAUS_MESSAGE or len(data) < 2:
        raise _Rejected(ElementRejection.UNSUPPORTED_ELEMENT_TYPE)
    try:
        payload = decode_payload(int.from_bytes(data[:2], "little"), data[2:])
    except JausDecodeError:
        payload = None
    if not isinstance(payload, SetLocalWaypoint):
        raise _Rejected(ElementRejection.UNSUPPORTED_ELEMENT_TYPE)
    return payload


__all__ = ["DEFAULT_TOLERANCE", "MAX_ELEMENTS", "QUERIES", "SERVICES", "WaypointList"]
