"""The TCP-ECB's watches: which nodes watch which patterns (globs over channel names), the
Names frames that tell them the channels that match, those the ECB knows when the Watch comes
and those named later, and the *pattern subscribers* of each channel.

A node that watches a pattern is a subscriber of every channel whose name matches it, from the
moment the ECB knows both: it is in the channel's Subscribers lists (``implied``), so a
publisher that names a new channel learns its pattern subscribers in the very answer that
tells it its exact ones, before its first event goes out. The node subscribes to the channel
itself too when its Names come (``Subscribe``); until then, and after, the pattern stands for
it. ``push(uid)`` tells the channel's publishers whenever its pattern subscribers change.

The ECB knows a channel's name while the channel has a subscriber or a publisher that gave it
(``TcpEcb._names``). A watcher is told only of channels its identity may subscribe to (with an
ACL). Bounds: ``MAX_WATCHES`` patterns per node (a Watch beyond is refused), patterns are
valid names (1..255 UTF-8 bytes, no control characters), and a Names frame lists at most
``NAMES_PER_FRAME`` channels (an answer takes as many frames as it needs).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Protocol

from ups import _tcpwire as w
from ups._channel import check_pattern, matches
from ups._errors import ConfigError
from ups._tcplink import Link

from ._acl import Acl

MAX_WATCHES = 64  #: patterns one node may watch at once
MAX_IMPLIED = 8192  #: channels one node may subscribe to by its patterns (then: implied_limited)


class Member(Protocol):
    """A registered node, as the watches see it."""

    link: Link | None
    identity: str | None


class Watches:
    """Patterns by node, over the ECB's tables: its names (UID -> name) and its registered
    nodes (node id -> member), both the ECB's own dicts."""

    def __init__(
        self,
        names: dict[int, str],
        members: Mapping[int, Member],
        acl: Acl | None,
        push: Callable[[int], None] = lambda uid: None,
    ) -> None:
        self._names = names
        self._members = members
        self._acl = acl
        self._push = push
        self._by_node: dict[int, set[str]] = {}  # node id -> its patterns
        self._by_pattern: dict[str, set[int]] = {}  # pattern -> node ids
        self._implied: dict[int, set[int]] = {}  # uid -> the nodes whose patterns match it
        self._implied_of: dict[int, set[int]] = {}  # node id -> the uids its patterns match
        #: node id -> its patterns not watched again yet since it came back (see ``renewing``)
        self._stale: dict[int, set[str]] = {}
        #: Watches refused for MAX_WATCHES; pattern subscriptions left out for MAX_IMPLIED
        self.counters = {"watch_limited": 0, "implied_limited": 0}

    def __len__(self) -> int:
        """Patterns watched, all nodes together."""
        return sum(len(p) for p in self._by_node.values())

    def implied(self, uid: int) -> set[int]:
        """The nodes that subscribe to ``uid`` by a pattern (empty set: none)."""
        return self._implied.get(uid, _NONE)

    def watches(self, node_id: int) -> bool:
        """Whether the node watches any pattern."""
        return bool(self._by_node.get(node_id))

    def implied_of(self, node_id: int) -> set[int]:
        """The channels the node subscribes to by its patterns (a copy)."""
        return set(self._implied_of.get(node_id, ()))

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
        self._stale.get(node_id, set()).discard(pattern)
        self._by_pattern.setdefault(pattern, set()).add(node_id)
        known = [
            (uid, name)
            for uid, name in self._names.items()
            if matches(pattern, name) and self._may(node_id, uid, name)
        ]
        for uid, _ in known:  # its publishers hear of it before the node hears the names
            self._imply(node_id, uid)
        for frame in _answer(pattern, known):
            self._send(node_id, frame)
        return None

    def unwatch(self, node_id: int, pattern: str) -> None:
        mine = self._by_node.get(node_id, set())
        mine.discard(pattern)
        nodes = self._by_pattern.get(pattern)
        if nodes is not None:
            nodes.discard(node_id)
            if not nodes:
                del self._by_pattern[pattern]
        for uid in list(self._implied_of.get(node_id, ())):
            name = self._names.get(uid)
            if name is None or not any(matches(other, name) for other in mine):
                self._unimply(node_id, uid)

    def forget(self, node_id: int) -> None:
        """The node left: it watches nothing any more."""
        self._stale.pop(node_id, None)
        for pattern in list(self._by_node.pop(node_id, ())):
            self.unwatch(node_id, pattern)
        for uid in list(self._implied_of.get(node_id, ())):
            self._unimply(node_id, uid)

    def renewing(self, node_id: int) -> None:
        """The node came back (a new link): what it does not watch again before its first
        Ping (``renewed``) it no longer watches. Meanwhile its patterns stand, so that its
        publishers do not drop it and take it back."""
        self._stale[node_id] = set(self._by_node.get(node_id, ()))

    def renewed(self, node_id: int) -> None:
        for pattern in self._stale.pop(node_id, ()):
            self.unwatch(node_id, pattern)

    def named(self, uid: int, name: str) -> None:
        """The ECB learnt ``uid``'s name: its matching watchers subscribe to it (their
        publishers are told), then each is told the name."""
        told: list[tuple[int, bytes]] = []
        for pattern, nodes in self._by_pattern.items():
            if matches(pattern, name):
                frame = w.encode(w.Names(pattern, ((uid, name),)))
                for node_id in nodes:
                    if self._may(node_id, uid, name):
                        self._imply(node_id, uid, push=False)
                        told.append((node_id, frame))
        if told:
            self._push(uid)
        for node_id, frame in told:
            self._send(node_id, frame)

    def unnamed(self, uid: int) -> None:
        """The ECB forgot ``uid``'s name (nobody subscribes to or publishes on it by name)."""
        for node_id in list(self._implied.get(uid, ())):
            self._unimply(node_id, uid)

    def _imply(self, node_id: int, uid: int, push: bool = True) -> None:
        if node_id in self._implied.get(uid, ()):
            return
        mine = self._implied_of.setdefault(node_id, set())
        if len(mine) >= MAX_IMPLIED:  # it still hears the name, and may subscribe itself
            self.counters["implied_limited"] += 1
            return
        mine.add(uid)
        self._implied.setdefault(uid, set()).add(node_id)
        if push:
            self._push(uid)

    def _unimply(self, node_id: int, uid: int) -> None:
        nodes = self._implied.get(uid)
        if nodes is None or node_id not in nodes:
            return
        nodes.discard(node_id)
        if not nodes:
            del self._implied[uid]
        implied = self._implied_of[node_id]
        implied.discard(uid)
        if not implied:
            del self._implied_of[node_id]
        self._push(uid)

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


_NONE: set[int] = set()  # never changed: what ``implied`` returns for a channel nobody watches


def _answer(pattern: str, known: list[tuple[int, str]]) -> Iterable[bytes]:
    """The Names frames that answer a Watch: ``NAMES_PER_FRAME`` channels each, the last
    ``done`` (an empty one when nothing matches)."""
    known, step = sorted(known), w.NAMES_PER_FRAME
    for start in range(0, max(len(known), 1), step):
        chunk = tuple(known[start : start + step])
        yield w.encode(w.Names(pattern, chunk, start + step >= len(known)))
