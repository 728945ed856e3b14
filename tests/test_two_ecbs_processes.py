"""Two ``ups can-broker`` processes on one udp_multicast bus (issue 29): whatever the order,
the delays, the recovery windows and the (random) instances, exactly one serves, a node
joins, and when the serving one goes the other takes over.

Each run: a CAN-ECB starts; after a random delay the other starts; after another random delay
a node joins (within 5 s). Then the status ports are asked until exactly one CAN-ECB serves
and the other stands by; the serving one is stopped, and a second node joins once the other
has taken over. RUNS runs, AT_ONCE at a time, each on a bus of its own (``UPS_DEEP=1``,
docs/development.md: three times as many). The seed is printed
(and given in a failure) so that a run can be repeated; the join and takeover times are
printed with ``-s``.
"""

from __future__ import annotations

import asyncio
import os
import random
import socket
import statistics
from dataclasses import dataclass
from pathlib import Path

import pytest

from ups import Node
from ups._tcpface import query_status

from .procs import Proc, private_multicast_bus

pytestmark = pytest.mark.netns

RUNS = 60 if os.environ.get("UPS_DEEP") == "1" else 20
AT_ONCE = 20  #: the runs mostly wait (their drawn delays, the takeover): 20 at once
JOIN = 5.0  #: a node joins within this long, with two CAN-ECBs on the bus
RECOVERIES = (0.2, 0.5, 2.0)  #: a recovery under a second makes a hasty newcomer (protocol.md)
SETTLE = 15.0  #: exactly one serves by then (docs/protocol.md, "one serving": 14 s)
TAKEOVER = 4.0  #: docs/protocol.md, Timers: a standing-by CAN-ECB takes over after this


@dataclass
class Run:
    number: int
    first_recovery: float
    second_recovery: float
    gap: float  #: between the two starts
    join_after: float  #: from the second start to the node's join
    joined: float = -1.0  #: how long the node took to join
    takeover: float = -1.0  #: from stopping the serving one to a new node's join


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ecb(bus: str, db: Path, recovery: float) -> tuple[Proc, str]:
    status = f"127.0.0.1:{_free_port()}"
    proc = Proc(
        "can-broker", "--can", bus, "--db", str(db), "--recovery", str(recovery),
        "--status", status,
    )  # fmt: skip
    return proc, status


async def _started(proc: Proc) -> None:
    await asyncio.to_thread(proc.wait_for_line, "CAN-ECB on")


async def _roles(statuses: list[str]) -> list[bool]:
    """Whether each CAN-ECB stands by, as its status port says."""
    return [bool((await query_status(s, 5.0))["stats"]["standby"]) for s in statuses]


async def _one_serves(statuses: list[str]) -> int:
    """The index of the one that serves, once exactly one does (the other stands by)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + SETTLE
    while True:
        standby = await _roles(statuses)
        if standby.count(False) == 1:
            return standby.index(False)
        if loop.time() > deadline:
            raise AssertionError(f"not exactly one serving after {SETTLE} s: standby={standby}")
        await asyncio.sleep(0.1)  # polling the status ports: a bounded wait for a state


async def _run(run: Run, tmp: Path) -> None:
    loop = asyncio.get_running_loop()
    bus = private_multicast_bus()
    first, first_status = _ecb(bus, tmp / f"{run.number}-a.db", run.first_recovery)
    procs = [first]
    try:
        await _started(first)
        await asyncio.sleep(run.gap)  # the scenario's delay between the starts
        second, second_status = _ecb(bus, tmp / f"{run.number}-b.db", run.second_recovery)
        procs.append(second)
        await _started(second)
        await asyncio.sleep(run.join_after)  # and before the node comes
        start = loop.time()
        async with Node(can=bus, node_id=0xE1EC_0000 + run.number, join_timeout=JOIN) as node:
            run.joined = loop.time() - start
            await node.subscribe(f"run/{run.number}")
        serving = await _one_serves([first_status, second_status])
        await asyncio.to_thread(procs[serving].stop)
        start = loop.time()
        takeover = TAKEOVER + max(run.first_recovery, run.second_recovery) + JOIN
        async with Node(can=bus, node_id=0xE1EC_1000 + run.number, join_timeout=takeover):
            run.takeover = loop.time() - start
        assert await _roles([(second_status, first_status)[serving]]) == [False]
    except BaseException as exc:
        logs = "".join(f"--- {p.args}\n{''.join(p.stderr_lines[-15:])}" for p in procs)
        raise AssertionError(f"{run}: {exc!r}\n{logs}") from exc
    finally:
        for proc in procs:
            await asyncio.to_thread(proc.stop)


@pytest.mark.timeout(240)
async def test_two_can_ecbs_leave_exactly_one_serving_whatever_the_order(tmp_path: Path) -> None:
    seed = int(os.environ.get("UPS_ELECTION_SEED", random.randrange(1 << 32)))
    print(f"seed {seed} (UPS_ELECTION_SEED)")
    rng = random.Random(seed)
    runs = [
        Run(
            number=i,
            first_recovery=rng.choice(RECOVERIES),
            second_recovery=rng.choice(RECOVERIES),
            gap=rng.uniform(0.0, 2.5),
            join_after=rng.uniform(0.0, 3.5),
        )
        for i in range(RUNS)
    ]
    slots = asyncio.Semaphore(AT_ONCE)

    async def limited(run: Run) -> None:
        async with slots:
            await _run(run, tmp_path)

    results = await asyncio.gather(*(limited(r) for r in runs), return_exceptions=True)
    failures = [str(r) for r in results if isinstance(r, BaseException)]
    joins = [r.joined for r in runs if r.joined >= 0]
    takeovers = [r.takeover for r in runs if r.takeover >= 0]
    for name, times in (("join", joins), ("join after takeover", takeovers)):
        if times:
            print(
                f"{name}: {len(times)} runs, median {statistics.median(times):.2f} s, "
                f"max {max(times):.2f} s"
            )
    assert not failures, f"seed {seed}: {len(failures)} of {RUNS} runs failed:\n" + "\n".join(
        failures
    )
