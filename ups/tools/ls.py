"""``ups ls``: the nodes and channels of a network in UPS terms.

On TCP/IP from the TCP-ECB's Status; on Zenoh from every node's status. Neither is on the
data path, so they know who subscribes to and publishes on what (and the channel names nodes
gave), not event rates:
``--rates`` subscribes to every channel for ``--listen-for`` seconds and counts.
On CAN from the CAN-ECB's database (TxNodes, etags) and a moment of listening to the bus (who
sends what, how often); names come from the catalog.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from .._cliargs import add_catalog, add_network, add_tls, positive_float, run_until_signal
from ._net import network_of

if TYPE_CHECKING:
    from .._catalog import Catalog
    from ._net import IpNetwork

HELP = "list the nodes and channels of a network"


def add_arguments(cmd: argparse.ArgumentParser) -> None:
    add_network(
        cmd, "a CAN bus: read its CAN-ECB's database and listen", "an IP network",
    )  # fmt: skip
    cmd.add_argument("--db", default=None, help="CAN: the CAN-ECB's database (default: the bus's)")
    cmd.add_argument(
        "--ecb", metavar="HOST:PORT", default=None,
        help="CAN: ask the CAN-ECB's status port (ups can-broker --status) instead of reading "
        "its database: from any host, and with who subscribes",
    )  # fmt: skip
    cmd.add_argument(
        "--listen-for", type=positive_float, default=1.0, metavar="S",
        help="seconds to listen for who sends what (CAN) or for rates (--rates) (default 1)",
    )  # fmt: skip
    cmd.add_argument(
        "--rates", action="store_true",
        help="TCP/IP, Zenoh: join, subscribe to every channel for --listen-for seconds, count "
        "events",
    )  # fmt: skip
    add_catalog(cmd)
    cmd.add_argument("--json", action="store_true", help="one JSON object")
    cmd.add_argument("--timeout", type=positive_float, default=5.0, help="seconds to wait")
    add_tls(cmd)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import json

    from .._catalog import load_catalog

    can, net = network_of(args)
    catalog = load_catalog(args.catalog)
    if can is not None:
        from .._bindings import default_db

        ecb = None
        if args.ecb is not None:  # its tables, subscribers included, from its status port

            async def ask_ecb() -> dict[str, Any]:
                from .._tcpquery import query_status

                return await query_status(args.ecb, args.timeout)  # plain TCP, no TLS

            ecb = asyncio.run(ask_ecb())
        db = args.db if args.db is not None else str(default_db(can))
        table = can_listing(can, None if ecb else db, args.listen_for, catalog, ecb)
        print(json.dumps(table, indent=2) if args.json else render_can(table))
        return 0
    assert net is not None

    async def ask() -> int:
        table = listing(await net.status(), catalog)
        if args.rates:
            await _count_rates(table, net, args)
        print(json.dumps(table, indent=2) if args.json else render(table))
        return 0

    return run_until_signal(ask())


MAX_RATED = 1024  #: --rates subscribes to at most as many channels (the rest show no rate)


async def _count_rates(table: dict[str, Any], net: IpNetwork, args: argparse.Namespace) -> None:
    """Add ``events_per_s`` to the channels of ``table``: events heard in ``--listen-for`` s."""
    import asyncio

    from .._channel import Channel

    channels = table["channels"][:MAX_RATED]
    counts = {int(c["uid"], 16): 0 for c in channels}
    if not counts:
        return
    async with net.node("ups-ls") as node:
        await node.subscribe(*[Channel(u) for u in counts], maxlen=65536)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + args.listen_for
        while (left := deadline - loop.time()) > 0:
            try:
                msg = await node.get_msg(timeout=left)
            except TimeoutError:
                break
            counts[msg.uid] += 1
        lost = node.stats().get("dropped", 0) + node.stats().get("lost", 0)
    for c in channels:
        c["events_per_s"] = round(counts[int(c["uid"], 16)] / args.listen_for, 1)
    table["lost_while_counting"] = lost


def listing(status: dict[str, Any], catalog: Catalog | None = None) -> dict[str, Any]:
    """The nodes and channels of a TCP-ECB's Status, each as a flat record; names the nodes
    did not give come from ``catalog``."""
    from .._catalog import Catalog

    catalog = catalog or Catalog()
    nodes = [
        {
            "node_id": n["node_id"],
            "name": n.get("name"),
            "identity": n.get("identity"),
            "address": n.get("address"),
            "connected": n.get("connected"),
            "subscribed": len(n.get("subscribed", ())),
            "published": len(n.get("published", ())),
        }
        for n in status.get("nodes", ())
    ]
    channels = [
        {
            "uid": c["uid"],
            "name": c.get("name") or catalog.channel(int(c["uid"], 16)).name,
            "publishers": list(c.get("publishers", ())),
            "subscribers": list(c.get("subscribers", ())),
        }
        for c in status.get("channels", ())
    ]
    stats = status.get("stats", {})
    return {
        "nodes": nodes,
        "channels": channels,
        "total": {"nodes": stats.get("nodes", len(nodes)),
                  "channels": stats.get("channels", len(channels))},
    }  # fmt: skip


def render(table: dict[str, Any]) -> str:
    """``listing`` as two aligned tables for a terminal."""
    names = {n["node_id"]: n["name"] for n in table["nodes"]}

    def who(ids: list[str]) -> str:
        return ", ".join(names.get(i) or i for i in ids) or "-"

    rows: list[tuple[str, ...]] = [
        ("NODE ID", "NAME", "IDENTITY", "ADDRESS", "LINK", "SUBS", "PUBS")
    ]
    rows += [
        (n["node_id"], n["name"] or "-", n["identity"] or "-", n["address"] or "-",
         "up" if n["connected"] else "down", str(n["subscribed"]), str(n["published"]))
        for n in table["nodes"]
    ]  # fmt: skip
    lines = [_counted(table["total"]["nodes"], "node"), *_aligned(rows), ""]
    rated = any("events_per_s" in c for c in table["channels"])
    rows = [("UID", "NAME", "PUBLISHERS", "SUBSCRIBERS", *(("EVENTS/S",) if rated else ()))]
    rows += [
        (c["uid"], c["name"] or "-", who(c["publishers"]), who(c["subscribers"]),
         *((str(c.get("events_per_s", "-")),) if rated else ()))
        for c in table["channels"]
    ]  # fmt: skip
    lines += [_counted(table["total"]["channels"], "channel"), *_aligned(rows)]
    if rated and len(table["channels"]) > MAX_RATED:
        lines.append(f"(rates of the first {MAX_RATED} channels only)")
    if table.get("lost_while_counting"):
        lines.append(f"lost {table['lost_while_counting']} events while counting: rates are low")
    return "\n".join(lines)


def _aligned(rows: Sequence[tuple[str, ...]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
            for row in rows]  # fmt: skip


def can_listing(
    bus: str, db: str | None, seconds: float, catalog: Catalog | None = None,
    ecb: dict[str, Any] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The nodes and channels of a CAN bus: its CAN-ECB's tables and what ``seconds`` of
    listening to the bus show (who sends, how often). The tables come from the CAN-ECB's
    status (``ecb``, from ``ups can-broker --status``: with who subscribes) or else from its
    database (``db``, read-only: on the CAN-ECB's host). Names come from ``catalog``."""
    import time

    from .. import _canproto as p
    from .._bindings import Bindings
    from .._canlink import open_bus
    from .._catalog import Catalog

    catalog = catalog or Catalog()
    subscribers: dict[int, list[int]] = {}  # uid -> TxNodes, when the CAN-ECB said
    if ecb is not None:
        try:
            txnodes = {int(n["node_id"], 16): int(n["txnode"], 16) for n in ecb["nodes"]}
            etags = {int(c["uid"], 16): int(c["etag"], 16) for c in ecb["channels"]}
            subscribers = {int(c["uid"], 16): [int(t, 16) for t in c["subscribers"]]
                           for c in ecb["channels"]}  # fmt: skip
        except (KeyError, TypeError, ValueError, AttributeError):
            from .._errors import ConfigError

            raise ConfigError("--ecb: that is not a CAN-ECB's status port "
                              "(ups can-broker --status)") from None  # fmt: skip
    else:
        assert db is not None
        bindings = Bindings()
        bindings.load_db(db)
        txnodes = {n: t for t, n in bindings.txnodes.items()}
        etags = {u: e for e, u in bindings.etags.items()}
    heard: dict[int, int] = {}  # TxNode -> frames
    sent: dict[int, dict[int, int]] = {}  # etag -> TxNode -> event frames
    listener = open_bus(bus)
    try:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            frame = listener.recv(left)
            if frame is None or not frame.is_extended_id or frame.is_error_frame:
                continue
            priority, txnode, etag = p.split_id(frame.arbitration_id)
            if txnode == p.MGMT_TXNODE:
                continue
            heard[txnode] = heard.get(txnode, 0) + 1
            if priority >= p.FIRST_EVENT_PRIORITY and etag >= p.FIRST_ETAG:
                senders = sent.setdefault(etag, {})
                senders[txnode] = senders.get(txnode, 0) + 1
    finally:
        listener.shutdown()
    uid_at = {e: u for u, e in etags.items()}
    node_at = {t: n for n, t in txnodes.items()}
    nodes = [
        {"node_id": f"0x{n:016x}", "txnode": f"0x{t:02x}", "heard": t in heard,
         "frames_per_s": round(heard.get(t, 0) / seconds, 1)}
        for n, t in sorted(txnodes.items(), key=lambda item: item[1])
    ]  # fmt: skip
    channels = []
    for etag in sorted(set(etags.values()) | set(sent)):
        uid = uid_at.get(etag)
        senders = sent.get(etag, {})
        channels.append({
            "uid": None if uid is None else f"0x{uid:016x}",
            "name": None if uid is None else catalog.channel(uid).name,
            "etag": f"0x{etag:04x}",
            "publishers": [f"0x{node_at[t]:016x}" if t in node_at else f"TxNode 0x{t:02x}"
                           for t in sorted(senders)],
            "subscribers": None if ecb is None else [  # the CAN-ECB's, in its memory only
                f"0x{node_at[t]:016x}" if t in node_at else f"TxNode 0x{t:02x}"
                for t in (subscribers.get(uid, ()) if uid is not None else ())
            ],
            "frames_per_s": round(sum(senders.values()) / seconds, 1),
        })  # fmt: skip
    return {"nodes": nodes, "channels": channels,
            "total": {"nodes": len(nodes), "channels": len(channels)}}  # fmt: skip


def render_can(table: dict[str, Any]) -> str:
    """``can_listing`` as two aligned tables for a terminal."""
    rows: list[tuple[str, ...]] = [("NODE ID", "TXNODE", "HEARD", "FRAMES/S")]
    rows += [
        (n["node_id"], n["txnode"], "yes" if n["heard"] else "no", str(n["frames_per_s"]))
        for n in table["nodes"]
    ]
    lines = [_counted(table["total"]["nodes"], "node"), *_aligned(rows), ""]
    subs = any(c["subscribers"] is not None for c in table["channels"])  # the CAN-ECB said
    rows = [("UID", "NAME", "ETAG", "PUBLISHERS HEARD", *(("SUBSCRIBERS",) if subs else ()),
             "FRAMES/S")]  # fmt: skip
    rows += [
        (c["uid"] or "(not bound)", c["name"] or "-", c["etag"],
         ", ".join(c["publishers"]) or "-",
         *((", ".join(c["subscribers"] or ()) or "-",) if subs else ()),
         str(c["frames_per_s"]))
        for c in table["channels"]
    ]  # fmt: skip
    lines += [_counted(table["total"]["channels"], "channel"), *_aligned(rows)]
    return "\n".join(lines)


def _counted(count: int, thing: str) -> str:
    """``1 node``, ``2 nodes``."""
    return f"{count} {thing}{'' if count == 1 else 's'}"
