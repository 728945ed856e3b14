"""The TCP-ECB's access control list: which identities may publish and subscribe which channels.

An ACL is a TOML file with one table per identity (a certificate's common name)::

    [identity.robot1]
    publish = ["robot1/*", "0x0123456789abcdef"]
    subscribe = ["fleet/commands"]

    [identity.operator]
    subscribe = ["*"]
    status = true          # may ask the broker for its tables (ups status), and every node
    node_ids = ["0x5b"]    # node ids only this identity may register

Each entry is a channel name (``robot1/speed``), a glob over names (``robot1/*``; ``*``, ``?``
and ``[...]`` as in shell patterns, ``*`` crossing ``/`` too), or a UID (``0x`` and hex digits).
A name or UID matches its channel whether the node gave the name or only the UID (the UID is the
name's hash). A glob matches only channels whose name the broker knows; the lone ``*`` matches
every channel. An identity that is not listed may do nothing: the ECB refuses even its Hello,
and since the ECB vouches for no node of it, subscribers admit none of its links for long.
``node_ids`` pins node ids (``0x`` and hex digits, or integers) to the identity: any other
identity saying Hello with one is refused from the ECB's first moment (``broker/_identities.py``
keeps the other bindings); a node id is pinned to one identity at most.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ups._channel import name_to_uid, parse_channel
from ups._errors import ConfigError
from ups._tomlfile import parse_toml, read_text

_GLOB = frozenset("*?[")
_KEYS = frozenset({"publish", "subscribe", "status", "node_ids"})
_TOP_ID = (1 << 64) - 1


@dataclass(frozen=True)
class _Patterns:
    """One list of entries, split by kind for matching."""

    everything: bool
    uids: frozenset[int]
    globs: tuple[str, ...]

    def match(self, uid: int, name: str | None) -> bool:
        if self.everything or uid in self.uids:
            return True
        return name is not None and any(fnmatch.fnmatchcase(name, g) for g in self.globs)


@dataclass(frozen=True)
class _Rights:
    publish: _Patterns
    subscribe: _Patterns
    status: bool
    node_ids: frozenset[int]


class Acl:
    """Rights by identity; ``allows`` answers one question, ``may_status`` another."""

    def __init__(self, rights: dict[str, _Rights], source: str = "<acl>") -> None:
        self._rights = rights
        self.source = source

    @classmethod
    def load(cls, path: str | Path) -> Acl:
        """Read an ACL file; a ``ConfigError`` names the file and what is wrong in it."""
        return cls.parse(read_text(path, "the ACL"), str(path))

    @classmethod
    def parse(cls, text: str, source: str = "<acl>") -> Acl:
        doc = parse_toml(text, source)
        extra = set(doc) - {"identity"}
        if extra:
            raise ConfigError(f"{source}: unknown top-level key {sorted(extra)[0]!r}; "
                              "expected only [identity.NAME] tables")  # fmt: skip
        identities = doc.get("identity", {})
        if not isinstance(identities, dict):
            raise ConfigError(f"{source}: 'identity' must be tables, [identity.NAME]")
        rights = {name: _rights(source, name, table) for name, table in identities.items()}
        pinned: dict[int, str] = {}
        for name, entry in rights.items():
            for node_id in sorted(entry.node_ids):
                other = pinned.setdefault(node_id, name)
                if other != name:
                    raise ConfigError(f"{source}: node id 0x{node_id:016x} is pinned to both "
                                      f"[identity.{other}] and [identity.{name}]")  # fmt: skip
        return cls(rights, source)

    def __contains__(self, identity: str | None) -> bool:
        return identity in self._rights

    def allows(self, identity: str | None, right: str, uid: int, name: str | None) -> bool:
        """Whether ``identity`` may ``right`` ("publish" or "subscribe") channel ``uid``, whose
        name is ``name`` when known."""
        rights = self._rights.get(identity) if identity is not None else None
        if rights is None:
            return False
        patterns = rights.publish if right == "publish" else rights.subscribe
        return patterns.match(uid, name)

    def may_status(self, identity: str | None) -> bool:
        rights = self._rights.get(identity) if identity is not None else None
        return rights is not None and rights.status

    def status_readers(self) -> tuple[str, ...]:
        """The identities that may read Status (the broker's, and every node's), sorted."""
        return tuple(sorted(name for name, rights in self._rights.items() if rights.status))

    def pins(self) -> dict[int, str]:
        """Node id -> the identity it is pinned to (``node_ids``)."""
        return {n: name for name, rights in self._rights.items() for n in rights.node_ids}

    def __len__(self) -> int:
        return len(self._rights)


def _rights(source: str, identity: str, table: Any) -> _Rights:
    where = f"{source}: [identity.{identity}]"
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    extra = set(table) - _KEYS
    if extra:
        raise ConfigError(f"{where}: unknown key {sorted(extra)[0]!r} "
                          f"(expected {', '.join(sorted(_KEYS))})")  # fmt: skip
    status = table.get("status", False)
    if not isinstance(status, bool):
        raise ConfigError(f"{where}: status must be true or false")
    return _Rights(
        _patterns(where, "publish", table.get("publish", [])),
        _patterns(where, "subscribe", table.get("subscribe", [])),
        status,
        _node_ids(where, table.get("node_ids", [])),
    )


def _node_ids(where: str, entries: Any) -> frozenset[int]:
    """``node_ids``: each a string (``0x`` and hex digits, or decimal) or an integer."""
    if not isinstance(entries, list):
        raise ConfigError(f'{where}: node_ids must be a list of node ids ("0x5b", ...)')
    ids: set[int] = set()
    for entry in entries:
        try:
            value = int(entry, 0) if isinstance(entry, str) else entry
        except ValueError:
            value = None
        if type(value) is not int or not 0 <= value <= _TOP_ID:
            raise ConfigError(f"{where}: node_ids entry {entry!r} is not a 64-bit node id "
                              "(0x and hex digits)")  # fmt: skip
        ids.add(value)
    return frozenset(ids)


def _patterns(where: str, key: str, entries: Any) -> _Patterns:
    if not isinstance(entries, list) or not all(isinstance(e, str) for e in entries):
        raise ConfigError(f"{where}: {key} must be a list of strings")
    uids: set[int] = set()
    globs: list[str] = []
    everything = False
    for entry in entries:
        try:
            if entry == "*":
                everything = True
            elif entry[:2].lower() == "0x":
                uids.add(parse_channel(entry).uid)
            elif _GLOB & set(entry):
                name_to_uid(entry)  # the same rules as a name: length, no control characters
                globs.append(entry)
            else:
                uids.add(name_to_uid(entry))
        except ConfigError as exc:
            raise ConfigError(f"{where}: {key} entry {entry!r}: {exc}") from None
    return _Patterns(everything, frozenset(uids), tuple(globs))
