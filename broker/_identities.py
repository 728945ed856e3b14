"""The TCP-ECB's node id <-> identity bindings (TLS): which identity may say Hello with a node id.

A node id pinned to an identity in the ACL (``node_ids``) belongs to it from the ECB's first
moment. Any other node id belongs to the identity that first registered it, for good: also
after the node left, and, with a file (``ups broker --identities FILE``), across restarts. The
file is read at start (one that cannot be read is an error then, never later) and written again,
whole, whenever a binding is made: to a temporary file beside it, synced, then renamed over it
(a crash leaves the old file or the new one, never a mix), by a thread, one write at a time,
each with every binding made until it starts. So after a restart an id is still its identity's,
and nobody can take it while its node comes back.

At most ``MAX_OWNERS`` ids are bound (pins aside). Past that a binding is forgotten to make room:
the oldest one of the binding identity whose node is not registered now, or, if it has none,
the oldest such binding of any identity. An identity that makes up node ids by the thousand so
forgets its own, not its neighbours'.

The file, UTF-8 JSON, oldest binding first::

    {"format": "ups-tcp-ecb-identities", "version": 1,
     "bindings": [["0x00000000000000a1", "alice"], ["0x00000000000000b0", "bob"]]}
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import logging
import os
import re
import time
from collections.abc import Container, Mapping
from pathlib import Path
from typing import Any

from ups._bindings import state_dir
from ups._errors import ConfigError

log = logging.getLogger("ups.tcp_ecb")

MAX_OWNERS = 1 << 16  #: node ids bound to the identity that registered them (pins aside)
FORMAT = "ups-tcp-ecb-identities"
VERSION = 1
_TOP_ID = (1 << 64) - 1


def default_file(listen: str) -> Path | None:
    """The file of a TCP-ECB listening on ``listen`` (HOST:PORT) in the state directory
    (``$UPS_STATE_DIR``, ``$XDG_STATE_HOME/ups`` or ``~/.local/state/ups``); None for port 0
    (any free port: another one at every start, so nothing to keep)."""
    host, _, port = listen.rpartition(":")
    if port in ("", "0"):
        return None
    slug = re.sub(r"[^A-Za-z0-9.]+", "_", f"{host}_{port}").strip("_")
    return state_dir() / f"tcp-ecb-{slug}-identities.json"


class Identities:
    """Node id -> identity: ``pins`` (fixed), and the bindings made (kept in ``path``, if any).
    ``counters`` gets ``identity_bindings`` (bound now) and ``identity_write_errors``."""

    def __init__(
        self, pins: Mapping[int, str], path: Path | None, counters: dict[str, int]
    ) -> None:
        self._pins = dict(pins)
        self.path = path
        self._counters = counters
        counters.setdefault("identity_bindings", 0)
        counters.setdefault("identity_write_errors", 0)
        self._owners: dict[int, str] = {}  # node id -> identity, oldest binding first
        self._by_identity: dict[str, dict[int, None]] = {}  # identity -> its ids, oldest first
        self._lock = -1
        self._writer: asyncio.Task[None] | None = None
        self._dirty = False  # bindings made since the last write started
        self._unsaved = False  # the last write failed: the next one (or close) tries again
        self._closed = False
        self._forgotten = 0
        self._logged_at = -1e9
        if path is not None:
            self._lock = _lock(path)
            try:
                self._load(path)
            except BaseException:
                os.close(self._lock)
                raise

    def __len__(self) -> int:
        return len(self._owners)

    def claim(self, node_id: int, identity: str, live: Container[int]) -> str | None:
        """``identity`` says Hello with ``node_id``: None if it may (the id is bound to it now,
        if it was free), else the identity that holds the id. ``live``: the node ids
        registered now (their bindings are not forgotten to make room)."""
        owner = self._pins.get(node_id) or self._owners.get(node_id)
        if owner is not None:
            return None if owner == identity else owner
        if len(self._owners) >= MAX_OWNERS:
            self._forget_one(identity, live)
        self._bind(node_id, identity)
        self._save()
        return None

    async def close(self) -> None:
        """Write what is not written yet, and let go of the file."""
        self._closed = True
        if self._writer is not None:  # it ends when every binding made is written
            with contextlib.suppress(Exception):
                await self._writer
        if self._unsaved and self.path is not None:
            await self._write(self._snapshot())
        if self._lock >= 0:
            os.close(self._lock)
            self._lock = -1

    # --- the table -------------------------------------------------------------------------

    def _bind(self, node_id: int, identity: str) -> None:
        self._owners[node_id] = identity
        self._by_identity.setdefault(identity, {})[node_id] = None
        self._counters["identity_bindings"] = len(self._owners)

    def _unbind(self, node_id: int) -> None:
        identity = self._owners.pop(node_id)
        mine = self._by_identity[identity]
        del mine[node_id]
        if not mine:
            del self._by_identity[identity]
        self._counters["identity_bindings"] = len(self._owners)

    def _forget_one(self, identity: str, live: Container[int]) -> None:
        """Make room: the identity's oldest binding of a node not registered now, else any
        identity's."""
        for ids in (self._by_identity.get(identity, {}), self._owners):
            gone = next((n for n in ids if n not in live), None)
            if gone is not None:
                self._forgotten += 1
                now = time.monotonic()
                if now - self._logged_at >= 1.0:
                    self._logged_at = now
                    log.warning("%d node ids are bound: forgot that %016x belongs to %s, to make "
                                "room (%d forgotten so far)", len(self._owners), gone,
                                self._owners[gone], self._forgotten)  # fmt: skip
                self._unbind(gone)
                return

    # --- the file --------------------------------------------------------------------------

    def _load(self, path: Path) -> None:
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            log.info("no node id bindings in %s yet: it is written at the first one", path)
            return
        except (OSError, UnicodeError) as exc:
            raise ConfigError(_unreadable(path, str(exc))) from None
        try:
            bindings = _parse(text)
        except (ValueError, TypeError, KeyError) as exc:
            raise ConfigError(_unreadable(path, str(exc))) from None
        for node_id, identity in bindings:
            pinned = self._pins.get(node_id)
            if pinned is not None:
                if pinned != identity:
                    log.warning("node id %016x is pinned to %s by the ACL: its binding to %s "
                                "in %s is dropped", node_id, pinned, identity, path)  # fmt: skip
                    self._unsaved = True  # written again without it
                continue
            self._bind(node_id, identity)
        log.info("node id bindings: %d kept in %s, %d pinned by the ACL", len(self._owners),
                 path, len(self._pins))  # fmt: skip

    def _snapshot(self) -> list[list[str]]:
        return [[f"0x{node_id:016x}", identity] for node_id, identity in self._owners.items()]

    def _save(self) -> None:
        """Write the bindings soon (one write at a time; what comes meanwhile, with the next)."""
        if self.path is None or self._closed:
            return
        self._dirty = True
        if self._writer is None:
            self._writer = asyncio.get_running_loop().create_task(self._write_all())

    async def _write_all(self) -> None:
        try:
            while self._dirty:
                self._dirty = False
                await self._write(self._snapshot())
        finally:
            self._writer = None

    async def _write(self, bindings: list[list[str]]) -> None:
        assert self.path is not None
        text = json.dumps({"format": FORMAT, "version": VERSION, "bindings": bindings})
        try:
            await asyncio.to_thread(_replace, self.path, text + "\n")
            self._unsaved = False
        except OSError as exc:
            self._counters["identity_write_errors"] += 1
            self._unsaved = True  # written with the next binding, or at close
            log.error("could not write the node id bindings to %s (%s): after a restart, the "
                      "ids bound since may be taken by others", self.path, exc)  # fmt: skip


def _parse(text: str) -> list[tuple[int, str]]:
    doc: Any = json.loads(text)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f'not a file of node id bindings (no "format": "{FORMAT}")')
    if doc.get("version") != VERSION:
        raise ValueError(f"version {doc.get('version')!r}, this is version {VERSION}")
    entries = doc["bindings"]
    if not isinstance(entries, list) or len(entries) > MAX_OWNERS:
        raise ValueError(f'"bindings" must be a list of at most {MAX_OWNERS} entries')
    seen: set[int] = set()
    bindings = []
    for entry in entries:
        if not (isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], str)):
            raise TypeError(f'a binding must be ["0x<node id>", "<identity>"]: {entry!r:.60}')
        text_id, identity = entry
        node_id = int(text_id, 16) if text_id[:2].lower() == "0x" else -1
        if not 0 <= node_id <= _TOP_ID or not isinstance(identity, str) or not identity:
            raise ValueError(f"not a node id and an identity: {entry!r:.60}")
        if node_id in seen:
            raise ValueError(f"node id {text_id} is bound twice")
        seen.add(node_id)
        bindings.append((node_id, identity))
    return bindings


def _unreadable(path: Path, why: str) -> str:
    return (
        f"cannot use the node id bindings in {path}: {why}. Move the file away to start "
        "afresh (every node id not pinned in the ACL is then free for the first identity that "
        "registers it)"
    )


def _replace(path: Path, text: str) -> None:
    """Write ``path`` whole or not at all: a synced temporary file renamed over it, and the
    rename synced too."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    with open(temporary, "w", encoding="utf-8") as out:
        out.write(text)
        out.flush()
        os.fsync(out.fileno())
    os.replace(temporary, path)
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def _lock(path: Path) -> int:
    """Hold ``PATH.lock`` exclusively: one TCP-ECB per file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(f"{path}.lock", os.O_RDONLY | os.O_CREAT, 0o644)
    except OSError as exc:
        raise ConfigError(f"cannot use the node id bindings in {path}: {exc}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise ConfigError(
            f"the node id bindings in {path} are in use by another TCP-ECB: give each its own "
            "--identities FILE"
        ) from None
    return fd
