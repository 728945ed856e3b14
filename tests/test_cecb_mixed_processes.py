"""A Python CAN-ECB (``ups can-broker``) and a C one (``ups c-ecb``, libups-ecb) on one
udp_multicast bus (issue 40): whichever starts first, whatever the delays and the recovery
windows, exactly one serves, every new node joins within 5 s, and when the serving one is
killed the other serves, and no event reaches a subscriber of another channel.

Each run: one kind starts, after a random delay the other; after another random delay a
subscriber of channel a and a publisher of a and b join (within 5 s each). The status ports
are asked until exactly one CAN-ECB serves; events flow (b's must not reach a's subscriber).
The serving one is killed (SIGKILL); a new node subscribes to channel c once the other has
taken over, and the publisher publishes on a, b and c until both subscribers have theirs:
every event either subscriber gets is of its own channel. RUNS runs, AT_ONCE at a time, each
on a bus of its own (``UPS_DEEP=1``: three times as many). The seed is printed (and given in a
failure) so that a run can be repeated (``UPS_ELECTION_SEED``).
"""

from __future__ import annotations

import asyncio
import os
import random
from dataclasses import dataclass
from pathlib import Path

import pytest

from ups import Node, Subscription

from .procs import Proc, private_multicast_bus
from .test_two_ecbs_processes import _one_serves, _roles, _started

pytestmark = pytest.mark.netns

RUNS = 60 if os.environ.get("UPS_DEEP") == "1" else 20
AT_ONCE = 20  #: the runs mostly wait (their drawn delays, the takeover): 20 at once
JOIN = 5.0  #: a node joins within this long, with two CAN-ECBs on the bus
RECOVERIES = (0.2, 0.5, 2.0)  #: a recovery under a second makes a hasty newcomer (protocol.md)
TAKEOVER = 4.0  #: docs/protocol.md, Timers: a standing-by CAN-ECB takes over after this
FLOWS = 20.0  #: events reach both subscribers by then: a bound for the test only
KINDS = {"python": ("can-broker", "--db", ".db"), "c": ("c-ecb", "--state", ".c-ecb")}


@dataclass
class Run:
    number: int
    first: str  #: the kind that starts first ("python" or "c")
    first_recovery: float
    second_recovery: float
    gap: float  #: between the two starts
    join_after: float  #: from the second start to the nodes' joins
    port: int  #: the first CAN-ECB's status port; the second's is the next
    served: str = ""  #: the kind that served until it was killed

    @property
    def kinds(self) -> tuple[str, str]:
        return (self.first, "c" if self.first == "python" else "python")


def _ecb(kind: str, bus: str, state: Path, recovery: float, port: int) -> tuple[Proc, str]:
    command, state_option, suffix = KINDS[kind]
    status = f"127.0.0.1:{port}"
    proc = Proc(
        command, "--can", bus, state_option, str(state.with_suffix(suffix)),
        "--recovery", str(recovery), "--status", status,
    )  # fmt: skip
    return proc, status


async def _flow(pub: Node, subs: dict[str, Subscription], names: dict[str, str]) -> None:
    """Publish on every channel of ``names`` (key -> name) until each subscription (by key) has
    an event; every event a subscription gets is of its own channel."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + FLOWS
    got = dict.fromkeys(subs, 0)
    serial = 0
    while not all(got.values()):
        if loop.time() > deadline:
            raise AssertionError(f"no event within {FLOWS} s: {got}")
        serial += 1
        for key in sorted(names, key=lambda k: k in subs):  # the others' first: markers last
            await pub.publish(names[key], f"{key}{serial}".encode())
        for key, sub in subs.items():
            while True:
                try:
                    msg = await sub.get_msg(timeout=0.2)
                except TimeoutError:
                    break
                assert msg.channel.name == names[key], f"{key} got {msg}"
                assert msg.data.startswith(key.encode()), f"{key} got {msg}"
                got[key] += 1


async def _run(run: Run, tmp: Path) -> None:
    bus = private_multicast_bus()
    names = {k: f"mixed/{run.number}/{k}" for k in "abc"}
    ids = [0xC0EC_0000 + 16 * run.number + i for i in range(3)]
    first, first_status = _ecb(
        run.kinds[0], bus, tmp / f"{run.number}-1", run.first_recovery, run.port
    )
    procs = [first]
    try:
        await _started(first)
        await asyncio.sleep(run.gap)  # the scenario's delay between the starts
        second, second_status = _ecb(
            run.kinds[1], bus, tmp / f"{run.number}-2", run.second_recovery, run.port + 1
        )
        procs.append(second)
        await _started(second)
        await asyncio.sleep(run.join_after)  # and before the nodes come
        statuses = [first_status, second_status]
        async with (
            Node(can=bus, node_id=ids[0], join_timeout=JOIN) as sub_node,
            Node(can=bus, node_id=ids[1], join_timeout=JOIN) as pub,
        ):
            sub_a = await sub_node.subscribe(names["a"])
            for key in "ab":
                await pub.advertise(names[key])
            serving = await _one_serves(statuses)
            run.served = run.kinds[serving]
            await _flow(pub, {"a": sub_a}, {k: names[k] for k in "ab"})
            await asyncio.to_thread(procs[serving].kill)
            takeover = TAKEOVER + max(run.first_recovery, run.second_recovery) + JOIN
            async with Node(can=bus, node_id=ids[2], join_timeout=takeover) as late:
                sub_c = await late.subscribe(names["c"])
                await pub.advertise(names["c"])
                await _flow(pub, {"a": sub_a, "c": sub_c}, names)
            assert await _roles([statuses[1 - serving]]) == [False]
    except BaseException as exc:
        logs = "".join(f"--- {p.args}\n{''.join(p.stderr_lines[-15:])}" for p in procs)
        raise AssertionError(f"{run}: {exc!r}\n{logs}") from exc
    finally:
        for proc in procs:
            await asyncio.to_thread(proc.stop)


@pytest.mark.timeout(240)
async def test_a_python_and_a_c_can_ecb_leave_exactly_one_serving(tmp_path: Path) -> None:
    seed = int(os.environ.get("UPS_ELECTION_SEED", random.randrange(1 << 32)))
    print(f"seed {seed} (UPS_ELECTION_SEED)")
    rng = random.Random(seed)
    # status ports below the ephemeral range (32768-60999), where no client connection of the
    # namespace takes them first, and each run's its own
    ports = rng.randrange(20_000, 30_000 - 2 * RUNS)
    runs = [
        Run(
            number=i,
            first=rng.choice(("python", "c")),
            first_recovery=rng.choice(RECOVERIES),
            second_recovery=rng.choice(RECOVERIES),
            gap=rng.uniform(0.0, 2.5),
            join_after=rng.uniform(0.0, 3.5),
            port=ports + 2 * i,
        )
        for i in range(RUNS)
    ]
    slots = asyncio.Semaphore(AT_ONCE)

    async def limited(run: Run) -> None:
        async with slots:
            await _run(run, tmp_path)

    results = await asyncio.gather(*(limited(r) for r in runs), return_exceptions=True)
    failures = [str(r) for r in results if isinstance(r, BaseException)]
    served = [r.served for r in runs]
    print(f"served first, then killed: python {served.count('python')}, c {served.count('c')}")
    assert not failures, f"seed {seed}: {len(failures)} of {RUNS} runs failed:\n" + "\n".join(
        failures
    )
