"""The TCP-ECB's Status: its registry as ``ups status`` and ``ups ls`` show it.

A Status lists at most ``STATUS_LIST`` nodes and ``STATUS_LIST`` channels, and for each at most
``STATUS_INNER`` of its channels or nodes; ``stats`` counts them all. Building one costs what
it lists, never what the registry holds: it takes the first nodes and channels in the order
they registered (no sort of every channel, no set of them all), and sorts only what it lists.
How often it is built is bounded too (``ups/_statuspacer.py``, ``StatusPacer``).
"""

from __future__ import annotations

import itertools
from collections.abc import Collection, Iterable, Mapping
from typing import Any

from ._tcpmember import Member

STATUS_LIST = 1000  #: nodes and channels listed in a Status at most (the rest are counted)
STATUS_INNER = 64  #: channels of a node, nodes of a channel, listed in a Status at most


def registry_status(
    members: Mapping[int, Member],
    subscribers: Mapping[int, Collection[int]],
    publishers: Mapping[int, Collection[int]],
    names: Mapping[int, str],
    stats: dict[str, int],
) -> dict[str, Any]:
    """The Status of a TCP-ECB whose tables these are (node id -> member; uid -> node ids)."""
    listed = list(itertools.islice(members.values(), STATUS_LIST))
    channels = sorted(_first_channels(subscribers, publishers))
    return {
        "node_id": _hex(0),
        "name": "ups-broker",
        "stats": stats,
        "listed": {"nodes": len(listed), "channels": len(channels), "at_most": STATUS_LIST},
        "nodes": [
            {
                "node_id": _hex(m.node_id),
                "name": m.name,
                "identity": m.identity,
                "address": f"{m.address[0]}:{m.address[1]}",
                "connected": m.link is not None,
                "subscribed": _listed(m.subs),
                "published": _listed(m.pubs),
                "channel_count": len(m.subs) + len(m.pubs),
            }
            for m in listed
        ],
        "channels": [
            {
                "uid": _hex(uid),
                "name": names.get(uid),
                "subscribers": _listed(subscribers.get(uid, ())),
                "publishers": _listed(publishers.get(uid, ())),
            }
            for uid in channels
        ],
    }


def _first_channels(
    subscribers: Mapping[int, object], publishers: Mapping[int, object]
) -> list[int]:
    """The first STATUS_LIST channels: subscribed ones, then ones only published on. It looks
    at fewer than 2 * STATUS_LIST channels (the ones it skips are all subscribed ones)."""
    first = list(itertools.islice(subscribers, STATUS_LIST))
    if len(first) < STATUS_LIST:
        only_published = (uid for uid in publishers if uid not in subscribers)
        first += itertools.islice(only_published, STATUS_LIST - len(first))
    return first


def _hex(value: int) -> str:
    return f"0x{value:016x}"


def _listed(values: Iterable[int]) -> list[str]:
    """At most STATUS_INNER of ``values`` (UIDs or node ids), in order, as hex."""
    return [_hex(v) for v in sorted(itertools.islice(values, STATUS_INNER))]
