"""The demo robot's navigator: odometry from the wheel encoder, a simulated GPS fix, and
steering toward the local waypoint that a JAUS Local Waypoint Driver sets.

* **Odometry** (dead reckoning): every ``PERIOD`` the navigator integrates the wheel
  encoder's latest speed (``robot/speed``, cm/s) and its own steering (a yaw rate) into a local
  pose, published on ``robot/local-pose``. The local frame is where the robot started: x north,
  y east (metres), yaw clockwise from north (radians, -pi..pi), as JAUS's local frame.
* **Steering**: toward the latest waypoint on ``robot/waypoint`` (x, y in the local frame), at
  most ``MAX_YAW_RATE``; before any waypoint, the robot drives a circle of ``LOITER_RADIUS``.
  It keeps steering toward a waypoint it has reached (so it circles it) until the next comes.
* **A simulated GPS fix** on ``robot/global-pose``, at the same rate: the local position seen
  from ``ORIGIN`` (WGS 84; an equirectangular projection, good to centimetres over kilometres),
  with Gaussian noise of ``GPS_SIGMA`` metres on each axis and ``HEADING_SIGMA`` radians on the
  yaw, and the position RMS that noise gives.

Every payload is integers, big-endian, with the scales of ``examples/robots.toml``: no floating
point on the wire. ``tests/test_navigation.py`` checks these layouts against the catalog.
"""

from __future__ import annotations

import asyncio
import math
import random
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ups import Message, Node

SPEED, LOCAL_POSE, GLOBAL_POSE, WAYPOINT = (
    "robot/speed",
    "robot/local-pose",
    "robot/global-pose",
    "robot/waypoint",
)
#: latitude and longitude (degrees) and altitude (metres) of the local frame's origin: the
#: position of the Report Global Pose worked example in docs/jaus.md
ORIGIN = (48.4, 9.95, 480.0)
EARTH_RADIUS = 6378137.0  #: metres, WGS 84's semi-major axis
PERIOD = 0.1  #: seconds between poses (10 Hz)
STEP = 0.02  #: seconds: the longest integration step (a late wake-up is integrated in steps)
MAX_YAW_RATE = 1.5  #: rad/s, the sharpest turn
STEER_GAIN = 2.0  #: yaw rate (rad/s) per radian of heading error
LOITER_RADIUS = 2.0  #: metres: the circle driven before any waypoint
GPS_SIGMA = 0.5  #: metres of noise on each axis of the fix
HEADING_SIGMA = 0.02  #: radians of noise on the fix's yaw

#: payload layouts (robots.toml): x, y in mm (i32), yaw in 1e-4 rad (i16); latitude and
#: longitude in 1e-7 degrees (i32), yaw in 1e-4 rad (i16), position RMS in cm (u16)
LOCAL_LAYOUT, GLOBAL_LAYOUT, WAYPOINT_LAYOUT = ">iih", ">iihH", ">ii"


def wrap(angle: float) -> float:
    """``angle`` in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclass
class Odometry:
    """The local pose, integrated from speed (m/s) and yaw rate (rad/s)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def step(self, speed: float, yaw_rate: float, dt: float) -> None:
        heading = self.yaw + yaw_rate * dt / 2  # the mean heading over the step
        self.x += speed * math.cos(heading) * dt
        self.y += speed * math.sin(heading) * dt
        self.yaw = wrap(self.yaw + yaw_rate * dt)

    def steer(self, speed: float, target: tuple[float, float] | None) -> float:
        """The yaw rate that turns toward ``target`` (else around the loiter circle)."""
        if target is None:
            return speed / LOITER_RADIUS
        error = wrap(math.atan2(target[1] - self.y, target[0] - self.x) - self.yaw)
        return max(-MAX_YAW_RATE, min(MAX_YAW_RATE, STEER_GAIN * error))

    def drive(self, speed: float, target: tuple[float, float] | None, dt: float) -> None:
        """``dt`` seconds of driving at ``speed``, steering all along (in short steps)."""
        steps = max(1, math.ceil(dt / STEP))
        for _ in range(steps):
            self.step(speed, self.steer(speed, target), dt / steps)

    def local_event(self) -> bytes:
        return struct.pack(LOCAL_LAYOUT, round(self.x * 1000), round(self.y * 1000),
                           _yaw(self.yaw))  # fmt: skip

    def global_event(self, rng: random.Random) -> bytes:
        """A GPS fix of this pose: latitude, longitude, yaw with noise, and its RMS."""
        lat0, lon0, _ = ORIGIN
        north = self.x + rng.gauss(0.0, GPS_SIGMA)
        east = self.y + rng.gauss(0.0, GPS_SIGMA)
        lat = lat0 + math.degrees(north / EARTH_RADIUS)
        lon = lon0 + math.degrees(east / (EARTH_RADIUS * math.cos(math.radians(lat0))))
        yaw = wrap(self.yaw + rng.gauss(0.0, HEADING_SIGMA))
        rms = round(math.sqrt(2) * GPS_SIGMA * 100)
        return struct.pack(GLOBAL_LAYOUT, round(lat * 1e7), round(lon * 1e7), _yaw(yaw), rms)


def _yaw(yaw: float) -> int:
    return max(-31416, min(31415, round(yaw * 10000)))  # within -pi..pi at 1e-4 rad


async def advertise(node: Node) -> None:
    """Bind the pose channels at their size (on CAN, a size class above one frame): done
    before anyone subscribes, they are bound once, not bound small and then moved."""
    await node.advertise(LOCAL_POSE, max_size=struct.calcsize(LOCAL_LAYOUT))
    await node.advertise(GLOBAL_POSE, max_size=struct.calcsize(GLOBAL_LAYOUT))


async def navigator(node: Node, stop: asyncio.Event) -> None:
    """Odometry, steering and the GPS fix, every PERIOD until ``stop``."""
    speed = 0.0  # m/s, the wheel encoder's latest
    waypoint: tuple[float, float] | None = None  # the latest

    def heard(msg: Message) -> None:
        nonlocal speed, waypoint
        if msg.channel.name == SPEED:
            (cm_s,) = struct.unpack(">h", msg.data)
            speed = cm_s / 100
            return
        x, y = (v / 1000 for v in struct.unpack(WAYPOINT_LAYOUT, msg.data))
        if waypoint != (x, y):
            print(f"navigator: heading for the waypoint x={x:.2f} m, y={y:.2f} m")
        waypoint = (x, y)

    await advertise(node)
    await node.subscribe(SPEED, WAYPOINT, callback=heard)
    odometry, rng = Odometry(), random.Random()
    loop = asyncio.get_running_loop()
    last = loop.time()
    while not stop.is_set():
        await asyncio.sleep(PERIOD)
        now = loop.time()
        odometry.drive(speed, waypoint, now - last)
        last = now
        await node.publish(LOCAL_POSE, odometry.local_event())
        await node.publish(GLOBAL_POSE, odometry.global_event(rng))
