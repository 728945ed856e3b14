"""The Local Waypoint List Driver: its list as a state machine (random inserts, bad links,
deletes, a full list, execution and poses, clients without control), asserting what must never
happen -- a request half applied, a link that lies, an active element outside the list, a
waypoint published out of order or without control, a reply to a client without control --
and the service end to end in one process: a JAUS OCU over real UDP loads a list, executes it,
and a CAN node receives each waypoint as the robot's poses reach the one before."""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from ups import Message, Node, jaus
from ups.broker.can_ecb import CanEcb
from ups.jaus import JausId, ReportLocalPose, SetLocalWaypoint
from ups.jaus._access import Access, State
from ups.jaus._host import JausHost
from ups.jaus._lists import (
    ALL_ELEMENTS,
    ConfirmElementRequest,
    DeleteElement,
    Element,
    ElementRejection,
    ExecuteList,
    QueryActiveElement,
    QueryElement,
    QueryElementCount,
    QueryElementList,
    RejectElementRequest,
    ReportActiveElement,
    ReportElement,
    ReportElementCount,
    ReportElementList,
    SetElement,
)
from ups.jaus._mapping import load_mapping
from ups.jaus._waypoint_list import WaypointList

from .conftest import eventually
from .procs import Proc, start_tcp_broker
from .test_jaus_component import Ocu

OCU, OTHER = JausId(2, 1, 1), JausId(3, 1, 1)
MAX = 6
UIDS = st.integers(0, 12) | st.just(ALL_ELEMENTS)


def waypoint_data(x: float, y: float, tolerance: float | None = None) -> bytes:
    code, body = jaus.encode_payload(SetLocalWaypoint(x, y, waypoint_tolerance=tolerance))
    return code.to_bytes(2, "little") + body


class ListMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.access = Access(minimum_authority=0, timeout=1e9)
        self.access.request(OCU, 10, 0.0, ("127.0.0.1", 3794))
        self.access.resume(OCU)
        self.replies: list[tuple[JausId, Any]] = []
        self.published: list[tuple[str, Any]] = []
        self.counters: dict[str, int] = {"refused_without_control": 0, "refused_not_ready": 0,
                                         "refused_in_emergency": 0}  # fmt: skip
        self.wl = WaypointList(
            access=self.access, carry_out=lambda n, m: self.published.append((n, m)),
            reply=lambda to, m: self.replies.append((to, m)), changed=lambda report: None,
            counters=self.counters, max_elements=MAX,
        )  # fmt: skip
        self.request = 0

    def _reply(self) -> Any:
        (to, msg), *rest = self.replies
        assert to == OCU and not rest
        self.replies.clear()
        return msg

    @rule(
        elements=st.lists(
            st.tuples(UIDS, UIDS, UIDS, st.integers(-5, 5), st.sampled_from([0, 0, 0, 1])),
            min_size=1,
            max_size=4,
        ),
        chain=st.booleans(),
    )
    def set_elements(self, elements: list[tuple[int, int, int, int, int]], chain: bool) -> None:
        if chain:  # a well-linked run after an existing element (or at the head)
            start = self.wl.order[-1] if self.wl.order else 0
            uids = [u for u in range(1, 13) if u not in self.wl.order][: len(elements)]
            links = [start, *uids, 0]
            elements = [(u, links[i], links[i + 2], e[3], e[4])
                        for i, (u, e) in enumerate(zip(uids, elements, strict=False))]  # fmt: skip
            if elements:  # the last names what follows the run now
                u, prev, _, x, kind = elements[-1]
                elements[-1] = (u, prev, 0, x, kind)
        if not elements:
            return
        before = list(self.wl.order), dict(self.wl.waypoints)
        self.request = (self.request + 1) & 0xFF
        request = SetElement(self.request, tuple(
            Element(uid, prev, nxt, waypoint_data(x, 0.0) if kind == 0 else b"\x01\x02", kind)
            for uid, prev, nxt, x, kind in elements))  # fmt: skip
        self.wl.handlers["SetElement"](OCU, request)
        answer = self._reply()
        if isinstance(answer, ConfirmElementRequest):
            assert answer.request_id == self.request
            for e in request.elements:  # every element is where it said, with its waypoint
                report = self.wl.answer("QueryElement", QueryElement(e.uid))
                assert isinstance(report, ReportElement)
                assert (report.element.previous, report.element.next) == (e.previous, e.next)
                assert report.element.data == e.data
        else:  # rejected: nothing changed
            assert isinstance(answer, RejectElementRequest) and answer.request_id == self.request
            assert (list(self.wl.order), dict(self.wl.waypoints)) == before
            if answer.response == ElementRejection.OUT_OF_MEMORY:
                assert len(before[0]) + len(elements) > MAX

    @rule(uids=st.lists(UIDS, min_size=1, max_size=3))
    def delete(self, uids: list[int]) -> None:
        before = list(self.wl.order)
        self.wl.handlers["DeleteElement"](OCU, DeleteElement(9, tuple(uids)))
        answer = self._reply()
        if isinstance(answer, ConfirmElementRequest):
            gone = set(before) if ALL_ELEMENTS in uids else set(uids)
            assert self.wl.order == [u for u in before if u not in gone]
        else:
            assert answer.response == ElementRejection.ELEMENT_NOT_FOUND
            assert self.wl.order == before and not set(uids) <= set(before) | {ALL_ELEMENTS}

    @rule(start=st.none() | UIDS)
    def execute(self, start: int | None) -> None:
        self.published.clear()
        self.wl.handlers["ExecuteList"](OCU, ExecuteList(1.5, start))
        first = self.wl.order[0] if start is None and self.wl.order else start
        if self.access.state != State.READY:
            assert not self.published and self.counters["refused_not_ready"] > 0
        elif first in self.wl.order:
            assert self.wl.active == first
            assert [n for n, _ in self.published] == ["SetTravelSpeed", "SetLocalWaypoint"]
            assert self.published[1][1] == self.wl.waypoints[first]
        else:
            assert not self.published
        assert not self.replies  # Execute List has no answer in JAUS

    @precondition(lambda self: self.wl.active != 0)
    @rule(reached=st.booleans())
    def pose(self, reached: bool) -> None:
        self.published.clear()
        active = self.wl.active
        goal = self.wl.waypoints[active]
        x = goal.x if reached else goal.x + 3.0  # the default tolerance is 1 m
        order = list(self.wl.order)
        at = order.index(active)
        following = order[at + 1] if at + 1 < len(order) else 0
        self.wl.moved(ReportLocalPose(x=x, y=goal.y))
        assert self.wl.order == order  # a pose never changes the list
        if not reached or self.access.state != State.READY:  # not there, or waiting
            assert self.wl.active == active and not self.published
            return
        assert self.wl.active == following
        expected = [("SetLocalWaypoint", self.wl.waypoints[following])] if following else []
        assert self.published == expected

    @rule(ready=st.booleans())
    def standby_or_resume(self, ready: bool) -> None:
        (self.access.resume if ready else self.access.standby)(OCU)

    @rule(name=st.sampled_from(["SetElement", "DeleteElement", "ExecuteList"]))
    def without_control(self, name: str) -> None:
        state = list(self.wl.order), self.wl.active
        refused = self.counters["refused_without_control"]
        message = {"SetElement": SetElement(1, (Element(11, 0, 0, waypoint_data(1, 1)),)),
                   "DeleteElement": DeleteElement(1, (ALL_ELEMENTS,)),
                   "ExecuteList": ExecuteList(1.0)}[name]  # fmt: skip
        self.published.clear()
        self.wl.handlers[name](OTHER, message)
        assert (list(self.wl.order), self.wl.active) == state
        assert not self.replies and not self.published
        assert self.counters["refused_without_control"] == refused + 1

    @invariant()
    def the_list_is_whole(self) -> None:
        order = self.wl.order
        assert len(order) == len(set(order)) <= MAX
        assert set(order) == set(self.wl.waypoints) and 0 not in order
        assert self.wl.active == 0 or self.wl.active in order
        listed = self.wl.answer("QueryElementList", QueryElementList())
        assert listed == ReportElementList(tuple(order))
        count = self.wl.answer("QueryElementCount", QueryElementCount())
        assert count == ReportElementCount(len(order))
        active = self.wl.answer("QueryActiveElement", QueryActiveElement())
        assert active == ReportActiveElement(self.wl.active)


TestListMachine = ListMachine.TestCase
TestListMachine.settings = settings(max_examples=200, stateful_step_count=30, deadline=None)


# --- end to end in one process ----------------------------------------------------------------

CATALOG = """
[channel."rover/goal"]
fields = [{ name = "x", type = "f32" }, { name = "y", type = "f32" }]
[channel."rover/cruise"]
fields = [{ name = "speed", type = "f32" }]
[channel."rover/odometry"]
fields = [{ name = "x", type = "f32" }, { name = "y", type = "f32" }]
"""
MAPPING = """catalog = "catalog.toml"
[message.SetLocalWaypoint]
channel = "rover/goal"
fields.x = "x"
fields.y = "y"
[message.SetTravelSpeed]
channel = "rover/cruise"
fields.speed = "speed"
[message.ReportLocalPose]
channel = "rover/odometry"
fields.x = "x"
fields.y = "y"
ignore = ["z", "position_rms", "roll", "pitch", "yaw", "attitude_rms", "timestamp"]
"""
ROBOT = JausId(1, 1, 1)


def active_is(uid: int) -> bytes:
    """Report Active Element, as an Event carries it: code, then the UID."""
    return (0x441E).to_bytes(2, "little") + uid.to_bytes(2, "little")


@pytest.fixture
async def rover(
    bus: str, ecb: CanEcb, tmp_path: Path
) -> AsyncIterator[tuple[JausHost, tuple[str, int], Node]]:
    (tmp_path / "catalog.toml").write_text(CATALOG)
    (tmp_path / "rover.jaus.toml").write_text(MAPPING)
    bridge = load_mapping(tmp_path / "rover.jaus.toml")
    async with Node(can=bus, node_id=0x3A) as face_node, Node(can=bus, node_id=0x3B) as wheels:
        host = JausHost(face_node, bridge, ROBOT, name="rover")
        address = await host.start("127.0.0.1", 0)
        yield host, address, wheels
        host.close()


async def test_an_ocu_loads_a_list_and_the_robot_drives_it_waypoint_by_waypoint(
    rover: tuple[JausHost, tuple[str, int], Node],
) -> None:
    host, address, wheels = rover
    ocu, other = Ocu(address, OCU), Ocu(address, OTHER)
    channel = {name: entry.channel for name, entry in host.component.bridge.items()}
    goals = await wheels.subscribe("rover/goal")
    cruise = await wheels.subscribe("rover/cruise")
    odometry = channel["ReportLocalPose"]
    await wheels.advertise("rover/odometry")
    services = await ocu.ask(jaus.QueryServices(), jaus.ReportServices)
    uris = {s.uri for node in services.nodes for c in node.components for s in c.services}
    assert {"urn:jaus:jss:mobility:LocalWaypointListDriver",
            "urn:jaus:jss:mobility:ListManager"} <= uris  # fmt: skip

    granted = await ocu.ask(jaus.RequestControl(10), jaus.ConfirmControl)
    assert granted.response == jaus.ControlResponse.CONTROL_ACCEPTED
    await ocu.send(jaus.Resume())
    points = [(5.0, 0.0), (5.0, 5.0), (0.0, 5.0)]
    chain = SetElement(1, tuple(
        Element(i + 1, i, i + 2 if i + 1 < len(points) else 0, waypoint_data(x, y, 0.5))
        for i, (x, y) in enumerate(points)))  # fmt: skip
    assert await ocu.ask(chain, ConfirmElementRequest) == ConfirmElementRequest(1)
    bad = SetElement(2, (Element(9, 1, 3, waypoint_data(1, 1)),))  # 1 is followed by 2, not 3
    rejected = await ocu.ask(bad, RejectElementRequest)
    assert rejected.response == ElementRejection.INVALID_NEXT_ELEMENT
    await other.send(DeleteElement(3, (ALL_ELEMENTS,)))  # no control: nothing happens
    listed = await ocu.ask(QueryElementList(), ReportElementList)
    assert listed.uids == (1, 2, 3)
    second = await ocu.ask(QueryElement(2), ReportElement)
    assert (second.element.previous, second.element.next) == (1, 3)

    await ocu.send(ExecuteList(2.0))
    speed = channel["SetTravelSpeed"].decode((await cruise.get_msg(timeout=5)).data)["speed"]
    assert speed == pytest.approx(2.0, abs=0.01)
    watcher, query = Ocu(address, JausId(4, 1, 1)), (0x241E).to_bytes(2, "little")
    for i, (x, y) in enumerate(points):
        goal = channel["SetLocalWaypoint"].decode((await goals.get_msg(timeout=5)).data)
        assert (goal["x"], goal["y"]) == pytest.approx((x, y), abs=1e-3)  # scaled on the way
        active = await ocu.ask(QueryActiveElement(), ReportActiveElement)
        assert active.uid == i + 1
        if i == 0:  # an every-change event on the active element: 1 at once
            confirm = await watcher.ask(
                jaus.CreateEvent(4, jaus.EventType.EVERY_CHANGE, 0, query),
                jaus.ConfirmEventRequest,
            )
            first = await watcher.next(jaus.Event)
            assert first.report_message == active_is(1)
        await wheels.publish("rover/odometry", odometry.encode({"x": x + 2, "y": y}))  # not yet
        await wheels.publish("rover/odometry", odometry.encode({"x": x + 0.3, "y": y}))  # there
    await eventually(lambda: host.component.waypoints.active == 0)  # type: ignore[union-attr]
    assert goals.pending == 0  # no waypoint after the last
    counters = host.stats()
    assert counters["waypoints_reached"] == 3 and counters["lists_completed"] == 1
    assert counters["refused_without_control"] >= 1
    changes: list[int] = []
    while not changes or changes[-1] != 0:  # 2, 3 (changes within 40 ms coalesce), then 0
        event = await watcher.next(jaus.Event)
        assert event.event_id == confirm.event_id
        changes.append(int.from_bytes(event.report_message[2:], "little"))
    assert changes == [*sorted(changes[:-1]), 0] and set(changes) <= {0, 2, 3}
    assert host.status()["jaus"]["waypoint_list"] == {"elements": 3, "active": 0}
    for client in (ocu, other, watcher):
        client.close()


async def test_ups_jaus_ocu_drives_a_robot_through_a_waypoint_list(tmp_path: Path) -> None:
    """As a user would: `ups broker`, `ups jaus --broker`, a robot node that reaches each goal
    it is given, and `ups jaus-ocu waypoints` following the list to its end."""
    (tmp_path / "catalog.toml").write_text(CATALOG)
    (tmp_path / "rover.jaus.toml").write_text(MAPPING)
    bridge = load_mapping(tmp_path / "rover.jaus.toml")
    goal_of, pose = bridge["SetLocalWaypoint"].channel, bridge["ReportLocalPose"].channel
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("jaus", "--listen", "127.0.0.1:0", "--map", str(tmp_path / "rover.jaus.toml"),
                      "--broker", address) as component:  # fmt: skip
        port = re.search(r"on 127\.0\.0\.1:(\d+)", component.wait_for_line("JAUS component"))
        assert port is not None
        async with Node(broker=address) as robot:
            reached: list[tuple[float, float]] = []

            async def drive(msg: Message) -> None:  # the robot is where it is sent at once
                goal = goal_of.decode(msg.data)
                reached.append((round(goal["x"], 3), round(goal["y"], 3)))
                await robot.publish("rover/odometry", pose.encode(goal))

            await robot.advertise("rover/odometry")
            goals = await robot.subscribe("rover/goal")
            driver = asyncio.create_task(_each(goals, drive))
            ocu = Proc("jaus-ocu", "--target", f"127.0.0.1:{port.group(1)}", "waypoints",
                       "5,0", "5,5", "0,5", "--speed", "1.5", "--poll", "0.05")  # fmt: skip
            code, out = await asyncio.to_thread(ocu.finish, 60)
            driver.cancel()
    assert code == 0, "".join(ocu.stderr_lines)
    lines = [json.loads(line) for line in out.splitlines()]
    assert (
        lines[0]["message"] == "ConfirmControl" and lines[1]["message"] == "ConfirmElementRequest"
    )
    actives = [line["active"] for line in lines[2:]]
    assert actives[-1] == 0 and actives[:-1] == sorted(actives[:-1])  # onwards, then done
    assert reached == [(5.0, 0.0), (5.0, 5.0), (0.0, 5.0)]  # each waypoint once, in order


async def _each(sub: Any, handle: Any) -> None:
    async for msg in sub:
        await handle(msg)
