"""``ups jaus-ocu waypoints``: take control, load a local waypoint list, execute it, and print
each waypoint the robot heads for, in the list's order, until the last is reached.

The component says which element is active (Report Active Element) on every change, by an
event (Create Event, every change, on Query Active Element); a question every ``--poll``
seconds keeps control (it lapses after the component's timeout of silence) and catches an
event lost on the way. A component drives its list from the head to the tail one element at
a time, so an element skipped between two answers (a change the component's rate cap merged
into the next, a datagram lost, or a component without events, asked only every ``--poll``
seconds) was active in between: it is printed before the later one, and every element is
printed once, in order, then ``{"active": 0}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from ups import ConfigError

from ._codec import JausId
from ._lists import ALL_ELEMENTS, NO_ELEMENT, Element
from ._messages import decode_payload, encode_payload
from ._messages import payloads as p
from ._ocu_link import Ocu, control_refused, to_json

EVENT_REQUEST, CANCEL_REQUEST = 3, 4  #: the request ids of the OCU's event on the list


def waypoints(ocu: Ocu, to: JausId | None, args: argparse.Namespace) -> int:
    if ocu.ra33:
        raise ConfigError("waypoints needs --framing judp: the List Manager's messages are "
                          "served in JUDP only")  # fmt: skip
    elements = _elements(args)
    source, reply = ocu.ask(p.RequestControl(args.authority), p.ConfirmControl, to)
    print(to_json(source, reply), flush=True)
    if reply.response != 0:
        print(f"ups jaus-ocu: {control_refused(ocu, to, source, reply)}", file=sys.stderr)
        return 1
    answered = p.ConfirmElementRequest | p.RejectElementRequest
    try:
        ocu.send(p.Resume(), to)
        _, status = ocu.ask(p.QueryStatus(), p.ReportStatus, to)
        if status.status != p.ManagementStatus.READY:  # the list would not run
            print(json.dumps({"error": f"the component is {status.status.name}, not READY"}))
            return 1
        ocu.ask(p.DeleteElement(1, (ALL_ELEMENTS,)), answered, to)
        source, reply = ocu.ask(p.SetElement(2, tuple(elements)), answered, to)
        print(to_json(source, reply), flush=True)
        if isinstance(reply, p.RejectElementRequest):
            return 1
        return _follow(ocu, to, [e.uid for e in elements], args)
    finally:  # sent, not awaited: a robot gone silent must not hide why we stopped
        ocu.send(p.ReleaseControl(), to)


def _elements(args: argparse.Namespace) -> list[Element]:
    """The list: one Set Local Waypoint per X,Y, UIDs 1, 2, ... from head to tail."""
    if args.tolerance is not None and args.tolerance > 100:
        raise ConfigError("--tolerance is at most 100 m (Set Local Waypoint's range)")
    if args.speed > 327.67:
        raise ConfigError("--speed is at most 327.67 m/s (Execute List's range)")
    elements = []
    for i, text in enumerate(args.points):
        try:
            x, y = (float(v) for v in text.split(","))
        except ValueError:
            raise ConfigError(f"a waypoint is X,Y in metres, not {text!r}") from None
        if not (abs(x) <= 100000 and abs(y) <= 100000):
            raise ConfigError(f"waypoint {text}: x and y are -100000..100000 m in JAUS")
        code, body = encode_payload(p.SetLocalWaypoint(x, y, waypoint_tolerance=args.tolerance))
        after = i + 2 if i + 1 < len(args.points) else NO_ELEMENT
        elements.append(Element(i + 1, i, after, code.to_bytes(2, "little") + body))
    return elements


class _Trail:
    """The elements printed so far, in list order; each one once."""

    def __init__(self, order: list[int]) -> None:
        self.order, self.at, self.done = order, -1, False

    def passed(self, uid: int) -> list[int]:
        """The elements to print now that ``uid`` is active: those not printed yet up to it
        (up to the tail and then 0 for 0: the list is done)."""
        if self.done or (uid != NO_ELEMENT and uid not in self.order):
            return []
        if uid == NO_ELEMENT:
            self.done = True  # seen first, 0 means the list never ran: nothing passed
            return [*(self.order[self.at + 1 :] if self.at >= 0 else []), NO_ELEMENT]
        i = self.order.index(uid)
        if i <= self.at:
            return []
        passed, self.at = self.order[self.at + 1 : i + 1], i
        return passed


def _follow(ocu: Ocu, to: JausId | None, order: list[int], args: argparse.Namespace) -> int:
    """Execute the list and print each active element until the list is done."""
    query = p.QueryActiveElement()
    code, body = encode_payload(query)
    create = p.CreateEvent(EVENT_REQUEST, p.EventType.EVERY_CHANGE, 0.0,
                           code.to_bytes(2, "little") + body)  # fmt: skip
    _, confirm = ocu.ask(create, p.ConfirmEventRequest | p.RejectEventRequest, to)
    event = confirm.event_id if isinstance(confirm, p.ConfirmEventRequest) else None
    trail = _Trail(order)
    try:
        ocu.send(p.ExecuteList(args.speed), to)
        # answered after Execute List: the events that came before it are older news
        _, first = ocu.ask(query, p.ReportActiveElement, to)
        _show(trail, first.uid)
        asked: float | None = None  # when the question still unanswered went out
        next_question = time.monotonic() + args.poll
        while not trail.done:
            now = time.monotonic()
            if now >= next_question:
                if asked is not None and now - asked > max(ocu.timeout, args.poll):
                    raise ConfigError(
                        f"no answer (Report Active Element) to Query Active Element from "
                        f"{ocu.where()} within {ocu.timeout:g} s"
                    )
                ocu.send(query, to)  # also what keeps control
                asked = asked if asked is not None else now
                next_question = now + args.poll
            got = ocu.receive(next_question)
            if got is None:
                continue
            active = _active(got[1], event)
            if isinstance(got[1], p.ReportActiveElement):
                asked = None
            if isinstance(got[1], p.RejectControl):
                print(f"ups jaus-ocu: {got[0]} took control back ({got[1].response.name}) "
                      f"before the list's end", file=sys.stderr)  # fmt: skip
                return 1
            if active is not None:
                _show(trail, active)
        return 0
    finally:
        if event is not None:
            ocu.send(p.CancelEvent(CANCEL_REQUEST, event), to)


def _active(payload: Any, event: int | None) -> int | None:
    """The active element a message tells of: a Report Active Element, or an Event of ours
    carrying one; None for anything else."""
    if isinstance(payload, p.ReportActiveElement):
        return int(payload.uid)
    if isinstance(payload, p.Event) and payload.event_id == event:
        message = payload.report_message
        report = decode_payload(int.from_bytes(message[:2], "little"), message[2:])
        if isinstance(report, p.ReportActiveElement):
            return int(report.uid)
    return None


def _show(trail: _Trail, uid: int) -> None:
    for passed in trail.passed(uid):
        print(json.dumps({"active": passed}), flush=True)


__all__ = ["waypoints"]
