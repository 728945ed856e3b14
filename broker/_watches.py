"""The TCP-ECB's watches: which nodes watch which patterns (globs over channel names), and the
Names frames that tell them the channels that match, those the ECB knows when the Watch comes
and those named later.

The ECB knows a channel's name while the channel has a subscriber or a publisher that gave it
(``TcpEcb._names``). A watcher is told only of channels its identity may subscribe to (with an
ACL). Bounds: ``MAX_WATCHES`` patterns per node (a Watch beyond is refused), patterns are
valid names (1..255 UTF-8 bytes, no control characters), and a Names frame lists at most
``NAMES_PER_FRAME`` channels (an answer takes as many frames as it needs).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Protocol

from ups import _tcpwire as w
from ups._channel import check_pattern, matches
from ups._errors import ConfigError
from ups._tcplink import Link

from ._acl import Acl

MAX_WATCHES = 64  #: patterns one node may watch at once


class Member(Protocol):
    """A registered node, as the watches see it."""

    link: Link | None
    identity: str | None


class Watches:
    """Patterns by node, over the ECB's tables: its names (UID -> name) and its registered
    nodes (node id -> member), both the ECB's own dicts."""

    def __init__(
        self, names: dict[int, str], members: Mapping[int, Member], acl: Acl | None
    ) -> None:
        self._names = names
        self._members = members
        self._acl = acl
        self._by_node: dict[int, set[str]] = {}  # node id -> its patterns
        self._by_pattern: dict[str, set[int]] = {}  # pattern -> node ids
        self.counters = {"watch_limited": 0}  #: Watches refused for MAX_WATCHES

    def __len__(self) -> int:
        """Patterns watched, all nodes together."""
        return sum(len(p) for p in self._by_node.values())

    def handle(self, node_id: int, frame: w.Watch | w.Unwatch) -> str | None:
        """A node's Watch or Unwatch; the reason to refuse it, or None."""
        if isinstance(frame, w.Watch):
            return self.watch(node_id, frame.pattern)
        self.unwatch(node_id, frame.pattern)
        return None

    def watch(self, node_id: int, pattern: str) -> str | None:
        """Start telling ``node_id`` of ``pattern``'s channels, and answer with those known now;
        or the reason it may not (for a Refused)."""
        try:
            check_pattern(pattern)
        except ConfigError as exc:
            return f"not a pattern: {exc}"
        mine = self._by_node.setdefault(node_id, set())
        if pattern not in mine and len(mine) >= MAX_WATCHES:
            self.counters["watch_limited"] += 1
            return f"a node may watch at most {MAX_WATCHES} patterns"
        mine.add(pattern)
        self._by_pattern.setdefault(pattern, set()).add(node_id)
        known = [
            (uid, name)
            for uid, name in self._names.items()
            if matches(pattern, name) and self._may(node_id, uid, name)
        ]
        for frame in _answer(pattern, known):
            self._send(node_id, frame)
        return None

    def unwatch(self, node_id: int, pattern: str) -> None:
        self._by_node.get(node_id, set()).discard(pattern)
        nodes = self._by_pattern.get(pattern)
        if nodes is not None:
            nodes.discard(node_id)
            if not nodes:
                del self._by_pattern[pattern]

    def forget(self, node_id: int) -> None:
        """The node left, or came back (and watches again what it still watches)."""
        for pattern in self._by_node.pop(node_id, ()):
            self.unwatch(node_id, pattern)

    def named(self, uid: int, name: str) -> None:
        """The ECB learnt ``uid``'s name: tell the nodes whose patterns match it."""
        for pattern, nodes in self._by_pattern.items():
            if matches(pattern, name):
                frame = w.encode(w.Names(pattern, ((uid, name),)))
                for node_id in nodes:
                    if self._may(node_id, uid, name):
                        self._send(node_id, frame)

    def _send(self, node_id: int, frame: bytes) -> None:
        member = self._members.get(node_id)
        if member is not None and member.link is not None:
            member.link.send_control(frame)

    def _may(self, node_id: int, uid: int, name: str) -> bool:
        """Whether the node may subscribe to the channel (with an ACL)."""
        member = self._members.get(node_id)
        if member is None or self._acl is None:
            return member is not None
        return self._acl.allows(member.identity, "subscribe", uid, name)


def _answer(pattern: str, known: list[tuple[int, str]]) -> Iterable[bytes]:
    """The Names frames that answer a Watch: ``NAMES_PER_FRAME`` channels each, the last
    ``done`` (an empty one when nothing matches)."""
    known, step = sorted(known), w.NAMES_PER_FRAME
    for start in range(0, max(len(known), 1), step):
        chunk = tuple(known[start : start + step])
        yield w.encode(w.Names(pattern, chunk, start + step >= len(known)))
