"""What the Zenoh benchmark's roles share (``benchmarks/zenoh_face.py``; the roles in
``_zenoh_rtt.py``, ``_zenoh_steps.py`` and ``_zenoh_gateway_role.py``): the keys, an event's
tag, the node ids and the bounds they agree on, and the clients they open: ``raw``, a plain
zenoh session with no UPS code, its publishers set as the Zenoh face sets its own (reliable,
congestion control DROP; ``congestion: block`` in the options makes ``put`` wait instead), and
``ups``/``tcp``, a UPS node on its Zenoh face or on TCP/IP, on uvloop (:func:`run`). Every
wait here is bounded.
"""

from __future__ import annotations

import asyncio
import json
import struct
import time
from collections.abc import Callable, Coroutine
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ups import Node

PING, PONG, DATA = "bench/zping", "bench/zpong", "bench/zdata"
TAG = struct.Struct("<IH2x")  # an event of a step: its number, the step
PROBE_STEP = 0xFFFF  # a marker event (the gateway's, a step's tail), not counted in any step
TAIL_PAUSE = 0.05  # s between a UPS source's last event of a step and its tail marker
SETUP_TIMEOUT = 20.0
IDLE = 1.0  # a sink's report: this long without an event of the step ends it
REPORT_LIMIT = 30.0  # a sink's report never waits longer than this
TICK = 0.001  # a paced source sends what is due, then sleeps until the next tick
YIELD_EVERY = 256  # a flat-out UPS source lets its loop run this often
IDS = {"pong": 0xBE7D_0001, "ping": 0xBE7D_0002, "sink": 0xBE7D_0003, "source": 0xBE7D_0004,
       "gateway": 0xBE7D_0005, "canpub": 0xBE7D_0006}  # fmt: skip


def run(main: Coroutine[Any, Any, Any]) -> Any:
    """On uvloop when installed, as ``ups`` runs its daemons."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(main)
    return uvloop.run(main)


def raw_session(endpoint: str) -> Any:
    """A plain zenoh client session of the router at ``endpoint`` (no scouting)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def raw_publisher(session: Any, key: str, options: dict[str, Any]) -> Any:
    import zenoh

    block = options.get("congestion") == "block"
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
        reliability=zenoh.Reliability.RELIABLE,
    )


def raw_matched(pub: Any) -> None:
    """Wait until a subscriber matches ``pub`` (a plain zenoh publisher)."""
    deadline = time.monotonic() + SETUP_TIMEOUT
    while not pub.matching_status.matching:
        if time.monotonic() > deadline:
            raise TimeoutError(f"no subscriber matched within {SETUP_TIMEOUT} s")
        time.sleep(0.005)


def ups_node(kind: str, endpoint: str, role: str) -> Node:
    from ups import Node

    zenoh, broker = (endpoint, None) if kind == "ups" else (None, endpoint)
    return Node(zenoh=zenoh, broker=broker, name=f"bench-z{role}", node_id=IDS[role],
                join_timeout=SETUP_TIMEOUT)  # fmt: skip


async def until(predicate: Callable[[], bool], what: str, interval: float = 0.005) -> None:
    deadline = time.monotonic() + (limit := SETUP_TIMEOUT + REPORT_LIMIT)
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} within {limit:.0f} s")
        await asyncio.sleep(interval)


def matched(node: Node, channel: str) -> Callable[[], bool]:
    """Whether a subscriber elsewhere matches ``channel`` (the Zenoh face knows)."""
    from ups import name_to_uid

    uid, elsewhere = name_to_uid(channel), node.face.subscribed_elsewhere  # type: ignore[attr-defined]
    return lambda: bool(elsewhere(uid))


def pipe_recv(conn: Connection, timeout: float = 600.0) -> Any:
    if not conn.poll(timeout):
        raise TimeoutError(f"no command within {timeout} s")
    return conn.recv()
