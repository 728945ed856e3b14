"""Demo: a small robot whose smart sensors and actuators talk over UPS on one CAN bus, and an
operator station that watches and commands it over TCP/IP through a gateway.

Runs in one process on a python-can ``virtual`` bus and loopback TCP, so it needs no hardware:

* a TCP-ECB (the TCP/IP registry) listens on a free loopback port;
* the gateway joins the bus and the TCP network; it hosts the bus's CAN-ECB, which hands out
  TxNodes and etags;
* a wheel encoder publishes ``robot/speed`` (cm/s, int16) at 20 Hz: 50 cm/s, or the limit it
  last got on ``robot/max-speed`` when that is lower;
* a sonar publishes ``robot/distance`` (cm, uint16) at 10 Hz, the obstacle coming closer;
* a motor controller subscribes to both and publishes ``robot/brake`` when an obstacle is
  near while the robot moves. It declares ``robot/brake`` a real-time channel (at most every
  50 ms, due on the bus within 2 ms): the CAN-ECB checks that the bus can guarantee it and
  gives it a priority above all best-effort traffic;
* a navigator (``navigation.py``) integrates the speed into the robot's local pose
  (``robot/local-pose``, odometry), simulates a GPS fix (``robot/global-pose``), both at 10 Hz,
  and steers toward the waypoint it last got on ``robot/waypoint``;
* a dashboard subscribes to everything and prints what it sees;
* the operator station, a TCP/IP node, subscribes to ``robot/speed`` and ``robot/brake``
  (the gateway forwards them from CAN, because someone on TCP subscribes) and publishes
  ``robot/max-speed`` (the gateway forwards it to CAN, because the encoder subscribes);
  with ``--jaus``, it stands aside while a JAUS operator controls the robot.

``ups demo`` (or ``scripts/demo``) runs it; it exits 0 when every channel was seen on CAN and
the operator saw the robot slow down to its limit and brake.
"""

from __future__ import annotations

import asyncio
import struct
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ups import ConfigError, Node
from ups.broker.tcp_ecb import TcpEcb
from ups.gateway import Gateway

from .navigation import GLOBAL_POSE, LOCAL_POSE, advertise, navigator

SPEED, DISTANCE, BRAKE, MAX_SPEED = (
    "robot/speed",
    "robot/distance",
    "robot/brake",
    "robot/max-speed",
)
NEAR_CM = 40
LIMIT_CM_S = 30
CRUISE_CM_S = 50


async def wheel_encoder(node: Node, stop: asyncio.Event) -> None:
    speed = CRUISE_CM_S
    limits = await node.subscribe(MAX_SPEED)
    while not stop.is_set():
        while limits.pending:
            msg = await limits.get_msg()
            (limit,) = struct.unpack(">h", msg.data)
            print(f"wheel-encoder: speed limit {limit} cm/s from TxNode 0x{msg.source:02x}")
            speed = max(0, min(CRUISE_CM_S, limit))
        await node.publish(SPEED, struct.pack(">h", speed))
        await asyncio.sleep(0.05)


async def sonar(node: Node, stop: asyncio.Event) -> None:
    distance = 200
    while not stop.is_set():
        await node.publish(DISTANCE, struct.pack(">H", distance))
        distance = max(10, distance - 15)
        await asyncio.sleep(0.1)


async def motor_controller(node: Node, stop: asyncio.Event) -> None:
    priority = await node.declare(BRAKE, period_ms=50, deadline_ms=2, size_bytes=1)
    print(f"motor-controller: {BRAKE} admitted as real-time, priority {priority:#04x}")
    sub = await node.subscribe(SPEED, DISTANCE)
    speed = distance = None
    braking = 0.0  # when the brake was last sent
    while not stop.is_set():
        try:
            msg = await sub.get_msg(timeout=0.2)
        except TimeoutError:
            continue
        if msg.channel.name == SPEED:
            (speed,) = struct.unpack(">h", msg.data)
        else:
            (distance,) = struct.unpack(">H", msg.data)
        near = distance is not None and distance < NEAR_CM and bool(speed)
        now = asyncio.get_running_loop().time()
        if near and now - braking >= 0.25:  # again while near: a brake command is a state
            await node.publish(BRAKE, b"\x01")
            braking = now


async def dashboard(node: Node, stop: asyncio.Event, seen: dict[str, int]) -> None:
    sub = await node.subscribe(SPEED, DISTANCE, BRAKE, LOCAL_POSE, GLOBAL_POSE)
    while not stop.is_set():
        try:
            msg = await sub.get_msg(timeout=0.2)
        except TimeoutError:
            continue
        name = msg.channel.name or str(msg.channel)
        seen[name] = seen.get(name, 0) + 1
        if name == BRAKE:
            if seen[name] == 1:
                txnode, priority = msg.source, msg.priority
                print(f"dashboard: BRAKE from TxNode 0x{txnode:02x} (priority {priority:#04x})")
        elif name == LOCAL_POSE:
            if seen[name] % 20 == 1:
                x, y, yaw = struct.unpack(">iih", msg.data)
                print(f"dashboard: {name} x={x / 1000:.2f} m y={y / 1000:.2f} m "
                      f"yaw={yaw / 10000:.2f} rad")  # fmt: skip
        elif name == GLOBAL_POSE:
            if seen[name] % 20 == 1:
                lat, lon = struct.unpack_from(">ii", msg.data)
                print(f"dashboard: {name} {lat / 1e7:.7f} {lon / 1e7:.7f}")
        elif seen[name] % 10 == 1:
            (value,) = struct.unpack(">h" if name == SPEED else ">H", msg.data)
            print(f"dashboard: {name} = {value} (from TxNode 0x{msg.source:02x})")


async def operator_station(
    node: Node,
    stop: asyncio.Event,
    seen: dict[str, int],
    jaus_controller: Callable[[], object | None] = lambda: None,
) -> None:
    """On TCP/IP: watch the robot through the gateway, and cap its speed while it is too fast;
    but while a JAUS operator controls the robot (``jaus_controller()`` names it: ``ups demo
    --jaus``), the speed is that operator's and the station stands aside."""
    sub = await node.subscribe(SPEED, BRAKE)
    sent = 0.0  # when the limit was last sent
    aside: object | None = None  # the JAUS operator the station stands aside for
    while not stop.is_set():
        try:
            msg = await sub.get_msg(timeout=0.2)
        except TimeoutError:
            continue
        name = msg.channel.name or str(msg.channel)
        seen[name] = seen.get(name, 0) + 1
        if name == BRAKE:
            if seen[name] == 1:
                print(f"operator (TCP): BRAKE via the gateway (priority {msg.priority:#04x})")
            continue
        (speed,) = struct.unpack(">h", msg.data)
        if speed <= LIMIT_CM_S:
            seen["slowed"] = 1
        holder = jaus_controller()
        if holder != aside:
            if holder is not None:
                print(f"operator (TCP): JAUS operator {holder} controls the robot; leaving "
                      f"{MAX_SPEED} to it")  # fmt: skip
            else:
                print(f"operator (TCP): no JAUS operator controls the robot; I cap it at "
                      f"{LIMIT_CM_S} cm/s again")  # fmt: skip
            aside = holder
        now = asyncio.get_running_loop().time()
        if aside is None and speed > LIMIT_CM_S and now - sent >= 0.5:
            # again until it slows: the first may go out before the gateway has told TCP/IP
            # that the encoder listens
            if not sent:
                print(f"operator (TCP): robot moves at {speed} cm/s; limiting it to {LIMIT_CM_S}")
            await node.publish(MAX_SPEED, struct.pack(">h", LIMIT_CM_S))
            sent = now


INTRO = """\
UPS demo: five robot parts on one CAN bus, an operator station on TCP/IP, a gateway between.
- Each CAN node joins the bus and gets a TxNode (its 7-bit sender number) from the CAN-ECB,
  the bus's broker, hosted here by the gateway.
- Channels have names (robot/speed); on CAN each one is bound to a 14-bit etag. Frames carry
  priority | TxNode | etag in their 29-bit identifier, nothing else.
- On TCP/IP the TCP-ECB keeps who subscribes to what; publishers send to subscribers direct.
- The gateway forwards only what someone on the other side subscribes to.
"""


def first_in_a_shell() -> str:
    """The line to type first in each new shell, when ``ups`` is not on its PATH (else none)."""
    from ups._extras import activation

    line = activation()
    return "" if line is None else f"\n  {line:<44} # first in each: puts ups on the PATH"


def _outro(local_ok: bool, remote_ok: bool, seen: dict[str, int], remote: dict[str, int]) -> str:
    verdict = "everything arrived" if local_ok and remote_ok else "something did NOT arrive"
    return f"""
In short: {verdict}. The dashboard (CAN) got {sum(seen.values())} events, the operator (TCP/IP)
{sum(remote.values())}; the brake went out at real-time priority 0x02 and crossed the gateway.

Try next (each in its own shell):{first_in_a_shell()}
  ups broker                                   # a TCP-ECB on 127.0.0.1:7411
  ups sub robot/speed --broker 127.0.0.1:7411
  ups pub robot/speed 0032 --broker 127.0.0.1:7411 --count 5
  ups ls --broker 127.0.0.1:7411               # who is there, by name
On a real bus: ups gateway --can socketcan:vcan0 --broker 127.0.0.1:7411, then --can nodes."""


JAUS_TRY = """\
JAUS component 1.1.1 of the robot on {where} (JUDP and RA 3.3; mapping examples/robot.jaus.toml):
the IGVC profile's Primitive Driver, Global and Local Pose Sensors, Velocity State Sensor, Local
Waypoint Driver and Local Waypoint List Driver, and the core services.
Try, in another shell (Ctrl-C here ends the demo):{first}
  ups jaus-ocu {target}discover
  ups jaus-ocu {target}query GlobalPose
  ups jaus-ocu {target}watch LocalPose --rate 10 --count 20
  ups jaus-ocu {target}waypoints 2,0 2,2 0,2 --speed 0.3
  ups jaus-ocu {target}send SetWrenchEffort propulsive_linear_x=20 --control --hold 10
The waypoints drive the robot around a square (the navigator says so here); the last command
limits it to 40 cm/s for 10 s (the wheel encoder says so). While a JAUS operator controls the
robot, the operator station on TCP/IP stands aside; when none does, it caps the speed at 30
cm/s again."""


async def jaus_face(bus: str, where: str) -> tuple[Node, Any]:
    """A JAUS component on the robot's bus, driving it through examples/robot.jaus.toml."""
    from ups.jaus import JUDP_PORT, JausId
    from ups.jaus._host import JausHost
    from ups.jaus._mapping import load_mapping
    from ups.jaus._serve import bind_error, parse_judp_address

    address, port = parse_judp_address(where)
    node = Node(can=bus, name="jaus", node_id=0x0D3E_00A0)
    await node.start()
    try:
        host = JausHost(node, load_mapping(Path(__file__).with_name("robot.jaus.toml")),
                        JausId(1, 1, 1), name="UPS demo robot")  # fmt: skip
        try:
            bound = await host.start(address, port)
        except OSError as exc:
            error = bind_error(f"{address}:{port}", exc)
            raise ConfigError(f"the JAUS component {error}; try --jaus HOST:PORT") from None
    except BaseException:
        await node.close()
        raise
    # ups jaus-ocu asks this host's 127.0.0.1:3794 (and the network, by broadcast) by default
    found = bound[1] == JUDP_PORT and bound[0] in ("127.0.0.1", "0.0.0.0")
    target = "" if found else f"--target {bound[0]}:{bound[1]} "
    print(JAUS_TRY.format(where=f"{bound[0]}:{bound[1]}", target=target, first=first_in_a_shell()),
          flush=True)  # fmt: skip
    return node, host


GRACE = 30.0  #: seconds the demo waits past its duration for events it has not seen yet


def _arrived(seen: dict[str, int], remote: dict[str, int]) -> tuple[bool, bool]:
    """Whether the dashboard (on the bus) and the operator (on TCP/IP) saw every kind of event."""
    local_ok = all(seen.get(ch) for ch in (SPEED, DISTANCE, BRAKE, LOCAL_POSE, GLOBAL_POSE))
    return local_ok, all(remote.get(ch) for ch in (SPEED, BRAKE, "slowed"))


async def run_demo(
    duration: float | None = 3.0, bus: str = "virtual:ups-demo", jaus: str | None = None
) -> int:
    """The demo in this process, for ``duration`` seconds and then until every kind of event
    arrived (at most ``GRACE`` s more; None: until cancelled, Ctrl-C); every part's task is
    ended and awaited before the nodes close, however it stops."""
    print(INTRO)
    with tempfile.TemporaryDirectory() as tmp:
        registry = TcpEcb("127.0.0.1", 0, recovery=0)  # any free port
        await registry.start()
        broker = f"127.0.0.1:{registry.port}"
        # a bus of this process only, a fresh table: nobody to hear out before serving
        gateway = Gateway(
            bus, broker, db=Path(tmp) / "gateway.db", node_id=0x0D3E_00FF, recovery=0.05
        )
        names = ("wheel-encoder", "sonar", "motor-controller", "dashboard", "navigator")
        nodes = [Node(can=bus, name=name, node_id=0x0D3E_0000 + i) for i, name in enumerate(names)]
        operator = Node(broker=broker, name="operator", node_id=0x0D3E_0100)
        jaus_host: Any = None

        def jaus_controller() -> object | None:
            """The JAUS operator controlling the robot, if any (the operator station asks)."""
            return None if jaus_host is None else jaus_host.component.access.holder

        stop = asyncio.Event()
        tasks: list[asyncio.Task[None]] = []
        try:
            await gateway.start()
            txnode = gateway.stats()["txnode"]
            print(f"gateway: on the bus as TxNode 0x{txnode:02x}, TCP-ECB at {broker}")
            for node in nodes:
                await node.start()
                print(f"{node.name}: joined as TxNode 0x{node.stats()['txnode']:02x}")
            await advertise(nodes[4])  # the poses, at their size, before anyone subscribes
            await operator.start()
            if jaus is not None:
                jaus_node, jaus_host = await jaus_face(bus, jaus)  # closed below
                nodes.append(jaus_node)
            seen: dict[str, int] = {}
            remote: dict[str, int] = {}
            encoder, sensor, controller, board, steering = nodes[:5]
            tasks = [
                asyncio.create_task(dashboard(board, stop, seen)),
                asyncio.create_task(operator_station(operator, stop, remote, jaus_controller)),
                asyncio.create_task(motor_controller(controller, stop)),
                asyncio.create_task(wheel_encoder(encoder, stop)),
                asyncio.create_task(sonar(sensor, stop)),
                asyncio.create_task(navigator(steering, stop)),
            ]
            if duration is None:
                await asyncio.Event().wait()  # until Ctrl-C
            await asyncio.sleep(duration or 0)
            # a busy machine may need longer for the whole story (a brake, the operator's answer)
            deadline = asyncio.get_running_loop().time() + GRACE
            while not all(_arrived(seen, remote)):
                if asyncio.get_running_loop().time() > deadline:
                    break
                await asyncio.sleep(0.1)
            stop.set()
            await asyncio.gather(*tasks)
            print(f"dashboard saw {seen}")
            print(f"operator saw {remote}")
            print(f"gateway: {gateway.stats()}")
            local_ok, remote_ok = _arrived(seen, remote)
            print(_outro(local_ok, remote_ok, seen, remote))
            return 0 if local_ok and remote_ok else 1
        finally:
            stop.set()
            for task in tasks:  # Ctrl-C: each part ends here, before its node closes
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            if jaus_host is not None:
                jaus_host.close()
            await operator.close()
            for node in nodes:
                await node.close()
            await gateway.close()
            await registry.close()


PARTS = ("wheel-encoder", "sonar", "motor-controller", "dashboard", "navigator", "operator")


async def run_part(part: str, can: str | None, broker: str | None, node_id: int) -> int:
    """One robot part as a process of its own (``python -m ups.examples.robots PART``): the CAN
    parts on ``can``, the operator on the TCP/IP network of ``broker``; until SIGTERM."""
    import signal

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    seen: dict[str, int] = {}
    on_tcp = part == "operator"
    async with Node(can=None if on_tcp else can, broker=broker if on_tcp else None,
                    name=part, node_id=node_id, join_timeout=30) as node:  # fmt: skip
        where = "on TCP/IP" if on_tcp else f"as TxNode 0x{node.stats()['txnode']:02x}"
        print(f"{part}: joined {where}", flush=True)
        if part == "wheel-encoder":
            await wheel_encoder(node, stop)
        elif part == "sonar":
            await sonar(node, stop)
        elif part == "motor-controller":
            await motor_controller(node, stop)
        elif part == "dashboard":
            await dashboard(node, stop, seen)
        elif part == "navigator":
            await navigator(node, stop)
        else:
            await operator_station(node, stop, seen)
    return 0


def main() -> None:
    import argparse
    import sys

    parser = argparse.ArgumentParser(description="one part of the demo robot, as a process")
    parser.add_argument("part", choices=PARTS)
    parser.add_argument("--can", help="the robot's CAN bus (python-can spec)")
    parser.add_argument("--broker", help="the TCP-ECB (for the operator)")
    parser.add_argument("--node-id", type=lambda t: int(t, 0), required=True)
    args = parser.parse_args()
    sys.stdout.reconfigure(line_buffering=True)  # type: ignore[union-attr]
    sys.exit(asyncio.run(run_part(args.part, args.can, args.broker, args.node_id)))


if __name__ == "__main__":
    main()
