"""Demo: a small robot whose smart sensors and actuators talk over UPS on one CAN bus.

Runs in one process on a python-can ``virtual`` bus, so it needs no hardware:

* the CAN-ECB hands out TxNodes and etags;
* a wheel encoder publishes ``robot/speed`` (cm/s, int16) at 20 Hz;
* a sonar publishes ``robot/distance`` (cm, uint16) at 10 Hz, the obstacle coming closer;
* a motor controller subscribes to both and publishes ``robot/brake`` when an obstacle is
  near while the robot moves. It declares ``robot/brake`` a real-time channel (at most every
  50 ms, due on the bus within 2 ms): the CAN-ECB checks that the bus can guarantee it and
  gives it a priority above all best-effort traffic;
* a dashboard subscribes to everything and prints what it sees.

``ups demo`` (or ``scripts/demo``) runs it; it exits 0 when every channel was seen.
"""

from __future__ import annotations

import asyncio
import struct
import tempfile
from pathlib import Path

from broker.can_ecb import CanEcb
from ups import Node
from ups._canlink import CanLink

SPEED, DISTANCE, BRAKE = "robot/speed", "robot/distance", "robot/brake"
NEAR_CM = 40


async def wheel_encoder(node: Node, stop: asyncio.Event) -> None:
    speed = 50
    while not stop.is_set():
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
    braking = False
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
        if near and not braking:
            await node.publish(BRAKE, b"\x01")
        braking = near


async def dashboard(node: Node, stop: asyncio.Event, seen: dict[str, int]) -> None:
    sub = await node.subscribe(SPEED, DISTANCE, BRAKE)
    while not stop.is_set():
        try:
            msg = await sub.get_msg(timeout=0.2)
        except TimeoutError:
            continue
        name = msg.channel.name or str(msg.channel)
        seen[name] = seen.get(name, 0) + 1
        if name == BRAKE:
            print(f"dashboard: BRAKE from TxNode {msg.source} (priority {msg.priority:#04x})")
        elif seen[name] % 10 == 1:
            (value,) = struct.unpack(">h" if name == SPEED else ">H", msg.data)
            print(f"dashboard: {name} = {value} (from TxNode {msg.source})")


async def run_demo(duration: float = 3.0, bus: str = "virtual:ups-demo") -> int:
    with tempfile.TemporaryDirectory() as tmp:
        link = CanLink.open(bus)
        ecb = CanEcb(link, Path(tmp) / "can-ecb.db")
        await ecb.start()
        names = ("wheel-encoder", "sonar", "motor-controller", "dashboard")
        nodes = [Node(can=bus, name=name, node_id=0x0D3E_0000 + i) for i, name in enumerate(names)]
        try:
            for node in nodes:
                await node.start()
                print(f"{node.name}: joined as TxNode {node.stats()['txnode']}")
            stop = asyncio.Event()
            seen: dict[str, int] = {}
            encoder, sensor, controller, board = nodes
            tasks = [
                asyncio.create_task(dashboard(board, stop, seen)),
                asyncio.create_task(motor_controller(controller, stop)),
                asyncio.create_task(wheel_encoder(encoder, stop)),
                asyncio.create_task(sonar(sensor, stop)),
            ]
            await asyncio.sleep(duration)
            stop.set()
            await asyncio.gather(*tasks)
            print(f"dashboard saw {seen}")
            print(f"CAN-ECB: {ecb.stats()}")
            return 0 if all(seen.get(ch) for ch in (SPEED, DISTANCE, BRAKE)) else 1
        finally:
            for node in nodes:
                await node.close()
            ecb.close()
            link.close()
