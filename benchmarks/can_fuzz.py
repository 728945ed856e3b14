"""CAN fuzzing: a CAN-ECB, a gateway and a plain node under a flood of random and semi-valid
frames, in one process on python-can ``virtual`` buses.

Each scenario sets up real nodes with real traffic, floods the bus with ``--frames`` frames from
a seeded generator (``--seed``) while the real publishers keep publishing, and then checks that
a new node can still join and bind. It prints, per target: frames sent, time and frames/s
processed (until the CAN-ECB and every node's queue are through the flood), the counters that
moved, TxNodes and etags held before and after, events delivered against events published
during the flood, wrong deliveries, and the process's RSS before and after.

    .venv/bin/python -m ups.benchmarks.can_fuzz --frames 100000 --seed 1

The generator (``FrameGen``, in :mod:`benchmarks._can_frames`) mixes random, semi-valid and
forged frames, part of the time aimed at the scenario's channels and nodes (``Targets``). What
a run watches and reports is in :mod:`benchmarks._fuzz_report`; its steps (warm up, flood,
settle, a late join) are in :mod:`benchmarks._fuzz_steps`.

Recovery windows open as the CAN-ECB decides: the flood's requests from TxNodes nobody holds
make it say Hello at most every 10 s, and the gateway's CAN-ECB then recovers for 2 s, the
standalone ones here for 0.2 s. The tests (tests/test_can_fuzz.py) pass ``recovery=0.2`` to
open exactly one short window at the flood's start instead (``prime_recovery``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

from ups import Node, name_to_uid
from ups._canlink import CanLink
from ups.benchmarks._can_frames import FrameGen
from ups.benchmarks._fuzz_report import (
    EcbWatch,
    Flow,
    Parts,
    Report,
    link_stats,
    numeric,
    watched,
)
from ups.benchmarks._fuzz_steps import (
    Scene,
    can_face,
    eventually,
    link_stats_of,
    open_raw,
    run_flood,
    targets_for,
    warm_up,
)
from ups.broker.can_ecb import CanEcb
from ups.broker.tcp_ecb import TcpEcb
from ups.gateway import Gateway

BIG = 1 << 20  #: subscription queues that never drop during a flood


# --- the scenarios ---------------------------------------------------------------------------


async def scenario_ecb(
    bus: str,
    workdir: Path,
    frames: int,
    seed: int,
    *,
    recovery: float | None = None,
    **targets: Any,
) -> Report:
    """A standalone CAN-ECB and three nodes: fz/a from P to S and Q, fz/b from P to S, fz/c
    from S to Q. Afterwards a fourth node joins, subscribes to fz/a and binds fz/new."""
    report = Report("CAN-ECB + nodes", seed, frames)
    raw = open_raw(bus)
    link = CanLink.open(bus)
    try:
        ecb = CanEcb(link, workdir / "ecb.db", recovery=0.2, max_channels=32)
        watch = EcbWatch(ecb)
        async with watched(report), contextlib.AsyncExitStack() as stack:
            await ecb.start()
            stack.callback(ecb.close)
            nodes = [Node(can=bus, node_id=0xF000 + i, join_timeout=10) for i in range(3)]
            for node in nodes:
                stack.push_async_callback(node.close)
            await asyncio.gather(*(n.start() for n in nodes))
            pub, sub, other = nodes
            txnodes = {n.node_id: can_face(n).txnode for n in nodes}
            real = {t for t in txnodes.values() if t is not None}
            a_to_s = Flow("fz/a P->S", "fz/a", pub, await sub.subscribe("fz/a", maxlen=BIG), real)
            flows = [
                a_to_s,
                Flow("fz/b P->S", "fz/b", pub, await sub.subscribe("fz/b", maxlen=BIG), real),
                Flow("fz/a P->Q", "fz/a", pub, await other.subscribe("fz/a", maxlen=BIG), real,
                     follows=a_to_s),
                Flow("fz/c S->Q", "fz/c", sub, await other.subscribe("fz/c", maxlen=BIG), real),
            ]  # fmt: skip
            await warm_up(flows)
            await eventually(lambda: not ecb.recovering)
            gen = FrameGen(seed, targets_for(ecb, ["fz/a", "fz/b", "fz/c"], real, **targets))
            parts = Parts()
            parts.add("can_ecb", lambda: numeric(ecb.stats()))
            parts.add("ecb link", lambda: link_stats(link))
            for name, node in zip("PSQ", nodes, strict=True):
                parts.add(f"node {name}", node.stats)
                parts.add(f"link {name}", link_stats_of(node))
            node_links = [can_face(n).link for n in nodes]
            scene = Scene(bus, raw, watch, link, node_links, nodes, txnodes, flows, parts)
            await run_flood(
                scene, report, gen, late=(0xF010, "fz/new", flows[0]), recovery=recovery
            )
    finally:
        link.close()
        raw.shutdown()
    return report


async def scenario_gateway(
    bus: str,
    workdir: Path,
    frames: int,
    seed: int,
    *,
    recovery: float | None = None,
    **targets: Any,
) -> Report:
    """A gateway (hosting the CAN-ECB) between the bus and a TCP-ECB on loopback. gw/up goes
    from CAN node CP to TCP node TS, gw/dn from TCP node TP to CAN node CS, gw/cc from CP to CS
    on CAN. Afterwards a new CAN node joins, subscribes to gw/dn and binds gw/new."""
    report = Report("gateway (CAN-ECB, CAN node, TCP node)", seed, frames)
    raw = open_raw(bus)
    tcp_ecb = TcpEcb("127.0.0.1", 0, recovery=0)
    await tcp_ecb.start()
    tcp_addr = f"127.0.0.1:{tcp_ecb.port}"
    try:
        async with watched(report), contextlib.AsyncExitStack() as stack:
            gw = Gateway(bus, tcp_addr, db=workdir / "gw.db", node_id=0x6A7E)
            stack.push_async_callback(gw.close)
            await gw.start()
            ecb, link, gw_can, gw_tcp = gw._ecb, gw._link, gw.can, gw.ip
            assert ecb is not None and link is not None and gw_can and gw_tcp
            watch = EcbWatch(ecb)
            cp = Node(can=bus, node_id=0xC0, name="can-pub", join_timeout=10)
            cs = Node(can=bus, node_id=0xC1, name="can-sub", join_timeout=10)
            tp = Node(broker=tcp_addr, node_id=0x70, name="tcp-pub")
            ts = Node(broker=tcp_addr, node_id=0x71, name="tcp-sub")
            for node in (cp, cs, tp, ts):
                stack.push_async_callback(node.close)
            await asyncio.gather(*(n.start() for n in (cp, cs, tp, ts)))
            can_nodes = [gw_can, cp, cs]
            txnodes = {n.node_id: can_face(n).txnode for n in can_nodes}
            real = {t for t in txnodes.values() if t is not None}
            gw_tx = can_face(gw_can).txnode
            assert gw_tx is not None
            flows = [
                Flow("gw/up CAN->TCP", "gw/up", cp, await ts.subscribe("gw/up", maxlen=BIG),
                     {gw_can.node_id}),
                Flow("gw/dn TCP->CAN", "gw/dn", tp, await cs.subscribe("gw/dn", maxlen=BIG),
                     {gw_tx}),
                Flow("gw/cc CAN->CAN", "gw/cc", cp, await cs.subscribe("gw/cc", maxlen=BIG),
                     real),
            ]  # fmt: skip
            await warm_up(flows)
            await eventually(lambda: not ecb.recovering)
            # forged events on gw/up's etag would reach TCP from the gateway's own node id,
            # indistinguishable from real ones: the generator sends none there
            up = ecb.etags[name_to_uid("gw/up")]
            names = ["gw/up", "gw/dn", "gw/cc"]
            gen = FrameGen(seed, targets_for(ecb, names, real, protected={up}, **targets))
            parts = Parts()
            parts.add("can_ecb", lambda: numeric(ecb.stats()))
            parts.add("gateway", gw.stats)
            parts.add("gateway link", lambda: link_stats(link))
            for name, node in (("gateway CAN", gw_can), ("CP", cp), ("CS", cs)):
                parts.add(f"node {name}", node.stats)
            for name, node in (("CP", cp), ("CS", cs)):
                parts.add(f"link {name}", link_stats_of(node))
            parts.add("node gateway TCP", gw_tcp.stats)
            parts.add("node TS", ts.stats)
            parts.add("node TP", tp.stats)
            node_links = [can_face(cp).link, can_face(cs).link]  # the gateway's CAN node: on link
            scene = Scene(bus, raw, watch, link, node_links, can_nodes, txnodes, flows, parts)
            scene.sizes = lambda: _gateway_sizes(gw, tcp_ecb)
            await run_flood(scene, report, gen, late=(0xC2, "gw/new", flows[1]), recovery=recovery)
    finally:
        await tcp_ecb.close()
        raw.shutdown()
    return report


def _gateway_sizes(gw: Gateway, tcp_ecb: TcpEcb) -> dict[str, int]:
    return {
        "forwarding_to_can": len(gw._to_can_sinks),
        "forwarding_to_tcp": len(gw._to_ip_sinks),
        "gateway_can_channels": len(gw.can._states) if gw.can else 0,
        "gateway_tcp_channels": len(gw.ip._states) if gw.ip else 0,
        "tcp_ecb_subscribed_channels": len(tcp_ecb._subscribers),
        "gateway_reconcile_backlog": len(gw._backlog.dirty),
    }


async def scenario_node(
    bus: str,
    workdir: Path,
    frames: int,
    seed: int,
    *,
    recovery: float | None = None,
    **targets: Any,
) -> Report:
    """Node N with ``filter_limit=0`` (it hears every frame and filters in software) subscribes
    to nd/a and nd/x and publishes nd/b; helper node H publishes nd/a and nd/x and subscribes to
    nd/b. A CAN-ECB serves the bus. Afterwards a new node joins, subscribes to nd/a, binds
    nd/new."""
    report = Report("node (filter_limit=0)", seed, frames)
    raw = open_raw(bus)
    link = CanLink.open(bus)
    try:
        ecb = CanEcb(link, workdir / "ecb.db", recovery=0.2, max_channels=32)
        watch = EcbWatch(ecb)
        async with watched(report), contextlib.AsyncExitStack() as stack:
            await ecb.start()
            stack.callback(ecb.close)
            target = Node(can=bus, node_id=0xD0, join_timeout=10, filter_limit=0)
            helper = Node(can=bus, node_id=0xD1, join_timeout=10)
            nodes = [target, helper]
            for node in nodes:
                stack.push_async_callback(node.close)
            await asyncio.gather(*(n.start() for n in nodes))
            txnodes = {n.node_id: can_face(n).txnode for n in nodes}
            real = {t for t in txnodes.values() if t is not None}
            flows = [
                Flow("nd/a H->N", "nd/a", helper, await target.subscribe("nd/a", maxlen=BIG),
                     real),
                Flow("nd/x H->N", "nd/x", helper, await target.subscribe("nd/x", maxlen=BIG),
                     real),
                Flow("nd/b N->H", "nd/b", target, await helper.subscribe("nd/b", maxlen=BIG),
                     real),
            ]  # fmt: skip
            await warm_up(flows)
            await eventually(lambda: not ecb.recovering)
            gen = FrameGen(seed, targets_for(ecb, ["nd/a", "nd/x", "nd/b"], real, **targets))
            target_link = can_face(target).link
            parts = Parts()
            parts.add("node N", target.stats)
            parts.add("link N", lambda: link_stats(target_link))
            parts.add("node H", helper.stats)
            parts.add("can_ecb", lambda: numeric(ecb.stats()))
            heard = can_face(target).bindings.heard
            node_links = [target_link, can_face(helper).link]
            scene = Scene(bus, raw, watch, link, node_links, nodes, txnodes, flows, parts)
            scene.sizes = lambda: {"node N heard Binds of etags": len(heard)}
            await run_flood(scene, report, gen, late=(0xD2, "nd/new", flows[0]), recovery=recovery)
    finally:
        link.close()
        raw.shutdown()
    return report


SCENARIOS = {"ecb": scenario_ecb, "gateway": scenario_gateway, "node": scenario_node}


async def _main(args: argparse.Namespace) -> None:
    for i, name in enumerate(args.targets.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            bus = f"virtual:can-fuzz-{name}-{i}-{time.monotonic_ns()}"
            report = await SCENARIOS[name](
                bus, Path(tmp), args.frames, args.seed, rivals=args.rivals, aim=args.aim
            )
            report.print()
            print(flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--targets", default="ecb,gateway,node", help="comma-separated")
    parser.add_argument(
        "--rivals",
        action="store_true",
        help="also Hello/Serving of any instance (the CAN-ECB may stand by for good)",
    )
    parser.add_argument(
        "--aim",
        type=float,
        default=0.1,
        help="how often an etag or UID field names a channel under test (default 0.1)",
    )
    parser.add_argument("--log", default="CRITICAL", help="log level of the daemons")
    args = parser.parse_args()
    logging.basicConfig(level=args.log)
    asyncio.run(_main(args))


if __name__ == "__main__":
    main()
