"""The demo robot's navigator (examples/navigation.py): odometry, steering toward a waypoint,
the simulated GPS fix, and payloads that are what the catalog (examples/robots.toml) and the
JAUS mapping (examples/robot.jaus.toml) say they are."""

from __future__ import annotations

import math
import random
import statistics
import struct

import pytest

from ups import name_to_uid
from ups._catalog import Catalog, ChannelSpec
from ups.examples import navigation as nav
from ups.jaus._mapping import load_mapping

from .procs import ROOT

CATALOG = Catalog.load(ROOT / "examples" / "robots.toml")


def spec_of(name: str) -> ChannelSpec:
    spec = CATALOG.get(name_to_uid(name))
    assert spec is not None, name
    return spec


def test_odometry_integrates_speed_and_yaw_rate() -> None:
    odometry = nav.Odometry()
    for _ in range(20):  # 2 s at 0.5 m/s, north
        odometry.step(0.5, 0.0, 0.1)
    assert odometry.x == pytest.approx(1.0) and odometry.y == odometry.yaw == 0.0
    for _ in range(100):  # a quarter turn to the right (clockwise: toward east) in 1 s
        odometry.step(0.0, math.pi / 2, 0.01)
    assert odometry.yaw == pytest.approx(math.pi / 2)
    odometry.step(1.0, 0.0, 1.0)  # 1 m east
    assert odometry.x == pytest.approx(1.0) and odometry.y == pytest.approx(1.0)
    for _ in range(300):  # turning on: the yaw stays in [-pi, pi)
        odometry.step(0.3, 1.0, 0.1)
        assert -math.pi <= odometry.yaw < math.pi


@pytest.mark.parametrize("target", [(2.0, 0.0), (0.0, 2.0), (-3.0, -1.0), (0.5, -0.5)])
def test_the_navigator_steers_to_a_waypoint_in_any_direction(target: tuple[float, float]) -> None:
    odometry = nav.Odometry(yaw=1.0)
    for _ in range(600):  # 60 s at most, at the demo's 30 cm/s
        odometry.drive(0.3, target, nav.PERIOD)
        if math.hypot(target[0] - odometry.x, target[1] - odometry.y) < 0.2:
            break
    assert math.hypot(target[0] - odometry.x, target[1] - odometry.y) < 0.2


def test_before_any_waypoint_it_circles() -> None:
    odometry = nav.Odometry()
    for _ in range(1000):
        odometry.drive(0.5, None, nav.PERIOD)
        # a circle of LOITER_RADIUS through the start, centred east of it
        assert math.hypot(odometry.x, odometry.y - nav.LOITER_RADIUS) == pytest.approx(
            nav.LOITER_RADIUS, abs=0.01
        )


def test_the_local_pose_event_is_the_catalogs_layout() -> None:
    odometry = nav.Odometry(x=12.345, y=-6.789, yaw=-2.5)
    spec = spec_of("robot/local-pose")
    values = spec.decode(odometry.local_event())
    assert values == {"x": pytest.approx(12.345), "y": pytest.approx(-6.789),
                      "yaw": pytest.approx(-2.5)}  # fmt: skip
    assert len(odometry.local_event()) == spec.size == struct.calcsize(nav.LOCAL_LAYOUT)


def test_the_waypoint_channel_is_what_the_navigator_reads() -> None:
    spec = spec_of("robot/waypoint")
    data = spec.encode({"x": 2.5, "y": -1.25})
    assert struct.unpack(nav.WAYPOINT_LAYOUT, data) == (2500, -1250)


def test_the_gps_fix_is_around_the_origin_with_its_documented_noise() -> None:
    spec = spec_of("robot/global-pose")
    odometry, rng = nav.Odometry(x=100.0, y=-50.0, yaw=0.3), random.Random(7)
    fixes = [spec.decode(odometry.global_event(rng)) for _ in range(2000)]
    lat, lon, yaw, rms = ([float(f[k]) for f in fixes] for k in ("lat", "lon", "yaw", "rms"))
    lat0, lon0, _ = nav.ORIGIN
    metres_per_degree = math.radians(nav.EARTH_RADIUS)
    north = [(v - lat0) * metres_per_degree for v in lat]
    east = [(v - lon0) * metres_per_degree * math.cos(math.radians(lat0)) for v in lon]
    assert statistics.mean(north) == pytest.approx(100.0, abs=0.1)
    assert statistics.mean(east) == pytest.approx(-50.0, abs=0.1)
    assert statistics.stdev(north) == pytest.approx(nav.GPS_SIGMA, rel=0.1)
    assert statistics.stdev(east) == pytest.approx(nav.GPS_SIGMA, rel=0.1)
    assert statistics.mean(yaw) == pytest.approx(0.3, abs=0.01)
    assert rms == [pytest.approx(math.sqrt(2) * nav.GPS_SIGMA, abs=0.01)] * len(rms)


def test_the_jaus_mapping_reports_the_navigators_poses() -> None:
    bridge = load_mapping(ROOT / "examples" / "robot.jaus.toml")
    odometry = nav.Odometry(x=3.0, y=4.0, yaw=1.5)
    local = bridge["ReportLocalPose"].from_ups(odometry.local_event())
    assert (local.x, local.y, local.yaw) == (3.0, 4.0, pytest.approx(1.5))
    fix = bridge["ReportGlobalPose"].from_ups(odometry.global_event(random.Random(1)))
    assert abs(fix.latitude - nav.ORIGIN[0]) < 1e-4 and abs(fix.longitude - nav.ORIGIN[1]) < 1e-4
    assert fix.altitude == nav.ORIGIN[2]  # the mapping's constant is the origin's altitude
