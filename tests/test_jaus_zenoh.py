"""A JAUS component on a Zenoh node (``ups jaus --zenoh``): an OCU's command reaches a UPS
subscriber across the router, a UPS publisher's event answers the OCU's query, and the
component shows in the Zenoh network's status, where the console reads it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from ups import Node, jaus
from ups._zenohstatus import network_status
from ups.jaus import JausId
from ups.jaus._host import JausHost
from ups.jaus._mapping import load_mapping

from .conftest import eventually
from .test_jaus_component import Ocu
from .test_jaus_mapping import GOOD, write

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("zenoh") is None, reason="eclipse-zenoh is not installed"
)


async def test_a_jaus_component_on_zenoh_drives_and_reports(
    zenoh_router: str, tmp_path: Path
) -> None:
    bridge = load_mapping(write(tmp_path, GOOD))
    async with (
        Node(zenoh=zenoh_router, node_id=0x1A, name="ups-jaus") as face_node,
        Node(zenoh=zenoh_router, node_id=0x1B) as robot,
    ):
        host = JausHost(face_node, bridge, JausId(1, 1, 1), name="rover")
        face_node.face.extra_status = host.status  # type: ignore[attr-defined]  # as ups jaus
        address = await host.start("127.0.0.1", 0)
        ocu = Ocu(address, JausId(2, 1, 1))
        try:
            limits = await robot.subscribe("robot/max-speed")
            await robot.advertise("robot/pose")
            granted = await ocu.ask(jaus.RequestControl(10), jaus.ConfirmControl)
            assert granted.response == jaus.ControlResponse.CONTROL_ACCEPTED
            await ocu.send(jaus.Resume())
            await ocu.send(jaus.SetWrenchEffort(propulsive_linear_x=40.0))
            limit = bridge["SetWrenchEffort"].channel.decode(
                (await limits.get_msg(timeout=10)).data
            )
            assert limit == {"limit": 80}  # 40 % at 2 cm/s per percent

            pose = bridge["ReportGlobalPose"].channel
            await robot.publish("robot/pose", pose.encode({"lat": 48.4, "lon": 9.95, "heading": 0}))
            await eventually(lambda: "ReportGlobalPose" in host.component.latest, timeout=10)
            report = await ocu.ask(jaus.QueryGlobalPose(0x0003), jaus.ReportGlobalPose)
            assert report.latitude == pytest.approx(48.4, abs=1e-6)

            status = await network_status(zenoh_router, timeout=5)
            (me,) = [n for n in status["nodes"] if n["node_id"] == f"0x{0x1A:016x}"]
            assert me["jaus"]["controller"] == "2.1.1" and me["jaus"]["state"] == "READY"
        finally:
            ocu.close()
            host.close()
