"""``ups ls``: the nodes and channels of a TCP/IP network, from its TCP-ECB, in UPS terms.

The TCP-ECB is not on the data path, so it knows who subscribes to and publishes on what (and
the channel names nodes gave it), not event rates.
"""

from __future__ import annotations

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
