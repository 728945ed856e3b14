"""The default 64-bit node id: stable across restarts, distinct between live processes.

A node id keys the node's TxNode at the CAN-ECB, so it must survive restarts (the node gets its
TxNode back) and differ between nodes that run at the same time (two senders of one identifier
is a bus error on CAN). The default is a hash of this machine's id, the node's name and a *slot*:
the lowest number whose lock file no live process holds. A restarted node takes slot 0 again; a
second copy running beside it takes slot 1.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import socket
from pathlib import Path
from typing import IO

_MAX_SLOTS = 1024


def _machine_id() -> str:
    for path in ("/etc/machine-id", "/var/lib/dbus/machine-id"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text:
            return text
    return socket.gethostname()


def _lock_dir() -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR")
    if not base:
        import tempfile  # only here: it imports shutil, bz2, lzma, random (0.8 MB of memory)

        base = tempfile.gettempdir()
    path = Path(base) / f"ups-{os.getuid()}"
    path.mkdir(mode=0o700, exist_ok=True)
    return path


def claim_node_id(name: str) -> tuple[int, IO[bytes]]:
    """Return a node id for ``name`` and the open lock file that reserves it while held."""
    stem = hashlib.sha256(f"{_machine_id()}\0{name}".encode()).hexdigest()[:16]
    lock_dir = _lock_dir()
    for slot in range(_MAX_SLOTS):
        handle = open(lock_dir / f"node-{stem}-{slot}.lock", "wb")  # noqa: SIM115 (held open)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            continue
        digest = hashlib.sha256(f"{_machine_id()}\0{name}\0{slot}".encode()).digest()
        return int.from_bytes(digest[:8], "big"), handle
    raise RuntimeError(f"more than {_MAX_SLOTS} live nodes named {name!r} on this machine")
