"""Every UPS node's status on a Zenoh network: ``ups status --zenoh`` and the operators' tools
get ``ups/@node/*`` (each node answers its own key: see ``_zenohface``)."""

from __future__ import annotations

import asyncio
import contextlib
import json
from pathlib import Path
from typing import Any

from ._errors import BrokerUnavailable
from ._zenohface import STATUS_PREFIX, zenoh_config


async def query_status(
    endpoint: str, config: str | Path | None = None, timeout: float = 5.0
) -> list[dict[str, Any]]:
    """The status of every UPS node and gateway on the Zenoh network at ``endpoint``."""
    conf = zenoh_config(endpoint, config)  # first: it says when Zenoh is not installed
    import zenoh

    def ask() -> list[dict[str, Any]]:
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise BrokerUnavailable(f"could not join Zenoh at {endpoint}: {exc}") from None
        try:
            answers = []
            replies = session.get(
                f"{STATUS_PREFIX}/*",
                target=zenoh.QueryTarget.ALL,  # every node's, not the best matching one's
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=timeout,
            )
            for reply in replies:
                if reply.ok is not None:
                    with contextlib.suppress(ValueError):
                        answers.append(json.loads(reply.ok.payload.to_string()))
            return answers
        finally:
            session.close()  # type: ignore[no-untyped-call]

    return await asyncio.to_thread(ask)


async def network_status(
    endpoint: str, config: str | Path | None = None, timeout: float = 5.0
) -> dict[str, Any]:
    """The UPS nodes and channels of a Zenoh network, from every node's status, in the shape
    of a TCP-ECB's Status (``nodes``, ``channels``), for the operators' tools."""
    answers = await query_status(endpoint, config, timeout)
    channels: dict[str, dict[str, Any]] = {}
    nodes = []
    for answer in answers:
        node_id = answer.get("node_id")
        if not isinstance(node_id, str):
            continue
        names = answer.get("names") or {}
        for role, key in (("subscribed", "subscribers"), ("published", "publishers")):
            for uid in answer.get(role) or ():
                entry = channels.setdefault(
                    uid, {"uid": uid, "name": None, "publishers": [], "subscribers": []}
                )
                entry[key].append(node_id)
                entry["name"] = entry["name"] or names.get(uid)
        nodes.append({
            "node_id": node_id,
            "name": answer.get("name"),
            "address": answer.get("zenoh_id"),
            "connected": True,
            "subscribed": list(answer.get("subscribed") or ()),
            "published": list(answer.get("published") or ()),
            **({"jaus": answer["jaus"]} if isinstance(answer.get("jaus"), dict) else {}),
        })  # fmt: skip
    return {
        "nodes": sorted(nodes, key=lambda n: n["node_id"]),
        "channels": [channels[uid] for uid in sorted(channels)],
    }
