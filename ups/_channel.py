"""Channels: 64-bit UIDs, given as an int or as a name mapped by a stable hash; and patterns,
globs over channel names.

A *pattern* is a name that contains ``*``, ``?`` or ``[`` (as in the TCP-ECB's access control
lists): ``*`` matches any characters, ``/`` too, ``?`` one, ``[...]`` one of a set, as in
shell patterns (``fnmatch``, case-sensitive). ``node.subscribe("robot/*")`` subscribes to every
channel whose name matches, now and later. A channel whose name really holds one of those
characters is subscribed to as ``Channel.named(name)``, by its UID, or by the pattern that
matches it alone (``robot/[*]``)."""

from __future__ import annotations

from typing import TypeGuard

from ._errors import ConfigError

UID_MAX = (1 << 64) - 1
NAME_MAX_BYTES = 255


class Channel:
    """An event channel: its 64-bit UID and, when it was given by name, that name.

    Immutable, compared and hashed by both. (A plain class: the command line imports it,
    and a dataclass costs milliseconds at start.)"""

    __slots__ = ("name", "uid")
    uid: int
    name: str | None

    def __init__(self, uid: int, name: str | None = None) -> None:
        object.__setattr__(self, "uid", uid)
        object.__setattr__(self, "name", name)

    def __setattr__(self, key: str, value: object) -> None:
        raise AttributeError(f"a Channel is immutable: cannot set {key}")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Channel):
            return NotImplemented
        return self.uid == other.uid and self.name == other.name

    def __hash__(self) -> int:
        return hash((self.uid, self.name))

    def __repr__(self) -> str:
        return f"Channel(uid={self.uid:#018x}, name={self.name!r})"

    def __str__(self) -> str:
        return self.name if self.name is not None else f"0x{self.uid:016x}"

    @classmethod
    def named(cls, name: str) -> Channel:
        """The channel called ``name``, taken as it is: never a pattern, whatever it holds."""
        return cls(name_to_uid(name), name)


#: the characters that make a name a pattern
PATTERN_CHARACTERS = frozenset("*?[")


def is_pattern(channel: object) -> TypeGuard[str]:
    """Whether ``channel`` is a pattern: a str holding ``*``, ``?`` or ``[``."""
    return isinstance(channel, str) and not PATTERN_CHARACTERS.isdisjoint(channel)


def check_pattern(pattern: str) -> str:
    """``pattern`` if it may be one (the rules of a name: 1..255 UTF-8 bytes, no control
    characters), else ``ConfigError``."""
    name_to_uid(pattern)
    return pattern


def matches(pattern: str, name: str | None) -> bool:
    """Whether the channel called ``name`` (None: a channel known only by its UID, which no
    pattern matches) matches ``pattern``."""
    if name is None:
        return False
    import fnmatch  # here: the command line imports this module

    return fnmatch.fnmatchcase(name, pattern)


def name_to_uid(name: str) -> int:
    """The UID of a channel name: the first 8 bytes of SHA-256(UTF-8 name), big-endian.

    Stable across runs, machines and Python versions, so every node maps a name alike.
    """
    import hashlib  # here, not at the top: the command line imports this module

    raw = name.encode("utf-8")
    if not raw or len(raw) > NAME_MAX_BYTES:
        raise ConfigError(f"channel name must be 1..{NAME_MAX_BYTES} UTF-8 bytes, got {name!r}")
    if any(ch < " " for ch in name):
        raise ConfigError(f"channel name must not contain control characters: {name!r}")
    return int.from_bytes(hashlib.sha256(raw).digest()[:8], "big")


ChannelLike = int | str | Channel


def as_channel(channel: ChannelLike) -> Channel:
    """Normalise an int UID, a name or a Channel into a Channel."""
    if isinstance(channel, Channel):
        return channel
    if isinstance(channel, bool):
        raise ConfigError(f"a channel is an int UID or a name, not {channel!r}")
    if isinstance(channel, int):
        if not 0 <= channel <= UID_MAX:
            raise ConfigError(f"channel UID must fit in 64 bits, got {channel:#x}")
        return Channel(channel)
    if isinstance(channel, str):
        return Channel(name_to_uid(channel), channel)
    raise ConfigError(f"a channel is an int UID or a name, not {type(channel).__name__}")


def as_literal(channel: ChannelLike) -> Channel:
    """``as_channel``, but a pattern is refused (``ConfigError``): where one channel is meant
    (publishing), never take a glob for the name of a channel."""
    if is_pattern(channel):
        raise ConfigError(
            f"{channel} is a pattern: publish on a channel (Channel.named({channel!r}) is the "
            "one so called)"
        )
    return as_channel(channel)


def parse_channel(text: str) -> Channel:
    """Parse a channel as written on the command line: ``0x`` + hex digits is a UID, else a name."""
    if text[:2].lower() == "0x":
        digits = text[2:]
        if not digits or not all(c in "0123456789abcdefABCDEF" for c in digits):
            msg = f"bad channel UID {text!r}: expected 0x followed by hex digits"
            raise ConfigError(msg)
        return as_channel(int(digits, 16))
    return as_channel(text)
