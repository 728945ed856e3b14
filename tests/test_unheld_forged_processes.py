"""Two real CAN-ECBs on one bus, and a forger who sends binding requests from a TxNode that no
node holds, one every few seconds (docs/protocol.md, *Watching the one that serves*). The one
that serves rightly leaves them unanswered (it counts them as ``unassigned``, and says Hello at
most once per Hello gap); the one that stands by must not take them for a silent CAN-ECB.

Before, the standing-by one watched every SUB_BIND and PUB_BIND it heard, took over 2.5 s
after each forged one, and the two swapped roles on and on, each swap a recovery window for
the whole bus. A forged Knock (answered by any serving CAN-ECB) and a real node's join and
binding in the middle of the attack are part of it. Over udp_multicast in a private network
namespace, each pair of kinds (Python, C, mixed) on a bus of its own, all at once.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from ups import Node, name_to_uid
from ups import _canproto as p

from .can_ecbs import can_ecb_proc
from .can_wire import Wire, wire
from .procs import Proc, private_multicast_bus
from .test_two_ecbs_processes import _free_port, _one_serves, _roles, _started

pytestmark = pytest.mark.netns

PAIRS = (("python", "python"), ("c", "c"), ("python", "c"))  #: the kinds, in start order
ANSWER = 2.5  #: docs/protocol.md, Timers: "answer"
HELLO_GAP = 10.0  #: docs/protocol.md, Timers: "Hello gap"
FORGE_EVERY = ANSWER + 0.5  #: each forged request is followed by more than the answer time
FORGED = 4  #: about 12 s of forged requests
JOIN = 10.0  #: a node's join limit
FORGER = 0x7E  #: the TxNode the forger sends from: the last a CAN-ECB gives out, held by nobody
UID = name_to_uid("forged/unheld")
ROLE_LINES = ("serves the bus again", "had no answer", "stands by and answers nothing")


def _forged(i: int) -> p.Management:
    """SUB_BIND, PUB_BIND, PUB_BIND(c) of TxNode FORGER, and a Knock, in turn."""
    return (
        p.Request(p.SUB_BIND, FORGER, UID + i),
        p.Request(p.PUB_BIND, FORGER, UID + i),
        p.Request(p.PUB_BIND, FORGER, UID + i, 2),
        p.Knock(),
    )[i % 4]


async def _attack(kinds: tuple[str, str], tmp: Path) -> None:
    bus = private_multicast_bus()
    statuses = [f"127.0.0.1:{_free_port()}" for _ in kinds]
    procs: list[Proc] = []
    try:
        with wire(bus) as listener:
            for i, kind in enumerate(kinds):
                state = tmp / f"{'-'.join(kinds)}-{i}"
                procs.append(can_ecb_proc(kind, bus, state, "--status", statuses[i]))
                await _started(procs[-1])
            serving = await _one_serves(statuses)
            async with Node(can=bus, node_id=0xA1, join_timeout=JOIN) as node:
                await node.subscribe("before/the/forger")
                lines = [len(proc.stderr_lines) for proc in procs]
                since = time.monotonic()
                await _forge(listener, bus, node)
                heard = listener.heard(since)
            standby = [True, True]
            standby[serving] = False
            assert await _roles(statuses) == standby  # the same one serves, all along
            assert sum(isinstance(m, p.Hello) for m in heard) <= (
                int((time.monotonic() - since) / HELLO_GAP) + 1
            ), heard  # the Hellos for unknown TxNodes, at most one per Hello gap
        for proc, before in zip(procs, lines, strict=True):
            log = "".join(proc.stderr_lines[before:])  # no role changed under the forger
            assert not any(line in log for line in ROLE_LINES), log
    except BaseException as exc:
        logs = "".join(f"--- {c.args}\n{''.join(c.stderr_lines[-15:])}" for c in procs)
        raise AssertionError(f"{kinds}: {exc!r}\n{logs}") from exc
    finally:
        for proc in procs:
            await asyncio.to_thread(proc.stop)


async def _forge(listener: Wire, bus: str, node: Node) -> None:
    """FORGED forged frames, one per FORGE_EVERY s; a new node joins and binds, and the joined
    one binds a new channel, in the middle of it."""
    for i in range(FORGED):  # bounded: the attack's own length
        listener.send(_forged(i))
        if i == FORGED // 2:
            async with Node(can=bus, node_id=0xB1, join_timeout=JOIN) as new:
                await new.subscribe("joined/under/the/forger")
            await node.subscribe("bound/under/the/forger")
        await asyncio.sleep(FORGE_EVERY)  # the attack's pace: each frame has its answer time


@pytest.mark.timeout(120)
async def test_requests_of_a_txnode_nobody_holds_swap_no_roles(tmp_path: Path) -> None:
    await asyncio.gather(*(_attack(kinds, tmp_path) for kinds in PAIRS))
