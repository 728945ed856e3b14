"""``ups ls``: the nodes and channels of a network in UPS terms.

On TCP/IP from the TCP-ECB's Status. The TCP-ECB is not on the data path, so it knows who
subscribes to and publishes on what (and the channel names nodes gave it), not event rates.
On CAN from the CAN-ECB's database (TxNodes, etags) and a moment of listening to the bus (who
sends what, how often).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any


def listing(status: dict[str, Any]) -> dict[str, Any]:
    """The nodes and channels of a TCP-ECB's Status, each as a flat record."""
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
            "name": c.get("name"),
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
    lines = [f"{table['total']['nodes']} nodes", *_aligned(rows), ""]
    rows = [("UID", "NAME", "PUBLISHERS", "SUBSCRIBERS")]  # the channels' table
    rows += [
        (c["uid"], c["name"] or "-", who(c["publishers"]), who(c["subscribers"]))
        for c in table["channels"]
    ]
    lines += [f"{table['total']['channels']} channels", *_aligned(rows)]
    return "\n".join(lines)


def _aligned(rows: Sequence[tuple[str, ...]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
            for row in rows]  # fmt: skip


def can_listing(bus: str, db: str, seconds: float) -> dict[str, Any]:
    """The nodes and channels of a CAN bus: its CAN-ECB's tables (read from the CAN-ECB's
    database, read-only: run it where the CAN-ECB runs) and what ``seconds`` of listening to
    the bus show (who sends, how often). Names are unknown on CAN."""
    import sqlite3
    import time
    from pathlib import Path

    from . import _canproto as p
    from ._canlink import open_bus
    from ._errors import ConfigError

    if not Path(db).is_file():
        raise ConfigError(
            f"no CAN-ECB database at {db}: give --db, on the host the CAN-ECB runs on"
        )
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as conn:
            txnodes = {int(n, 16): t for n, t in conn.execute("SELECT * FROM txnodes")}
            etags = {int(u, 16): e for u, e in conn.execute("SELECT * FROM etags")}
    except sqlite3.Error as exc:
        raise ConfigError(f"cannot read the CAN-ECB database {db}: {exc}") from None
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
            "name": None,
            "etag": f"0x{etag:04x}",
            "publishers": [f"0x{node_at[t]:016x}" if t in node_at else f"TxNode 0x{t:02x}"
                           for t in sorted(senders)],
            "subscribers": [],  # known to the CAN-ECB only in memory
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
    lines = [f"{table['total']['nodes']} nodes", *_aligned(rows), ""]
    rows = [("UID", "ETAG", "PUBLISHERS HEARD", "FRAMES/S")]
    rows += [
        (c["uid"] or "(not bound)", c["etag"], ", ".join(c["publishers"]) or "-",
         str(c["frames_per_s"]))
        for c in table["channels"]
    ]  # fmt: skip
    lines += [f"{table['total']['channels']} channels", *_aligned(rows)]
    return "\n".join(lines)
