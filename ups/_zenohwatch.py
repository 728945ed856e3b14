"""Pattern subscriptions on Zenoh: channel names travel in key expressions
(``ups/<UID>/<name>``, when the publisher knows the name), so a Zenoh subscriber on every key a
pattern can match hears each named channel's events. See docs/protocol.md, "UPS on Zenoh".

The first event of a channel that the node does not subscribe to yet makes the channel known
(the face's ``found``: the node joins it to the pattern's subscriptions and declares its own
subscriber of it, ``ups/<UID>/**``). Until that subscriber is declared, the channel's events
come through the pattern's subscriber; once it is, the pattern's subscriber leaves them to it.
An event that both hand over in the moment between is delivered once: by its number, for
UPS publishers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ._channel import PATTERN_CHARACTERS, Channel, matches, name_to_uid
from ._errors import ConfigError
from ._face import Found

PREFIX = "ups"
#: what a chunk of a key expression cannot hold as it is, the glob characters included
_KEY_SPECIAL = PATTERN_CHARACTERS | frozenset("$#")
MAX_OVERLAPS = 4096  #: (publisher, channel) pairs handed over at once, at most (then forgotten)


def pattern_key(pattern: str) -> str:
    """The key expression that covers every named channel ``pattern`` may match: its chunks
    before the first one with a wildcard (or one a key cannot hold as it is), then ``**``."""
    literal: list[str] = []
    for chunk in pattern.split("/"):
        if not chunk or chunk[0] == "@" or not _KEY_SPECIAL.isdisjoint(chunk):
            break
        literal.append(chunk)
    return "/".join([PREFIX, "*", *literal, "**"])


def named_key(key: str) -> tuple[int, str] | None:
    """The UID and name of a key ``ups/<UID>/<name>``, or None for any other key."""
    parts = key.split("/", 2)
    if len(parts) != 3 or parts[0] != PREFIX or len(parts[1]) != 16:
        return None
    try:
        return int(parts[1], 16), parts[2]
    except ValueError:
        return None


class ZenohWatches:
    """The patterns a Zenoh face watches. ``subscribed`` is the face's own table of per-channel
    subscribers (UID -> subscriber), ``expected`` its next number per (publisher, UID)."""

    def __init__(self, subscribed: dict[int, Any], expected: dict[tuple[int, int], int]) -> None:
        self._subscribed = subscribed
        self._expected = expected
        self._watching: dict[str, tuple[Any, Found]] = {}  # pattern -> (subscriber, found)
        self._overlap: set[tuple[int, int]] = set()  # pairs whose events came by a pattern

    def declare(
        self, session: Any, pattern: str, found: Found, receive: Callable[[int, Any, str], None]
    ) -> None:
        """Subscribe to ``pattern``'s keys; ``receive(uid, sample, name)`` is called (in a Zenoh
        thread) with each event of a matching channel the face does not subscribe to itself."""

        def on_sample(sample: Any) -> None:  # in a Zenoh thread
            named = named_key(str(sample.key_expr))
            if named is None or named[0] in self._subscribed:  # its own subscriber has it
                return
            if matches(pattern, named[1]):
                receive(named[0], sample, named[1])

        subscriber = session.declare_subscriber(pattern_key(pattern), on_sample)
        self._watching[pattern] = (subscriber, found)

    def undeclare(self, pattern: str) -> None:
        entry = self._watching.pop(pattern, None)
        if entry is not None:
            try:
                entry[0].undeclare()
            except Exception:  # the session is closing: it goes with it
                return

    def discovered(self, uid: int, name: str) -> bool:
        """An event of ``uid`` came by a pattern, under ``name``: whether the name is the UID's
        (else the event is not delivered); the patterns that match it are told of the channel."""
        try:
            if name_to_uid(name) != uid:
                return False
        except ConfigError:
            return False
        channel = Channel(uid, name)
        for pattern, (_, found) in list(self._watching.items()):
            if matches(pattern, name):
                found(channel)
        return True

    def duplicate(self, source: int, uid: int, seq: int, by_pattern: bool) -> bool:
        """Whether this UPS event was delivered already, by the other way in: events of one
        channel come by the pattern's subscriber until the face's own is declared, and one may
        come by both in the moment between."""
        key = (source, uid)
        expected = self._expected.get(key)
        if by_pattern:
            if len(self._overlap) >= MAX_OVERLAPS:
                self._overlap.clear()
            self._overlap.add(key)
            return expected is not None and seq < expected
        if key not in self._overlap:
            return False
        if expected is not None and seq < expected:
            return True
        self._overlap.discard(key)  # the face's own subscriber has taken over
        return False

    def close(self) -> None:
        for pattern in list(self._watching):
            self.undeclare(pattern)
