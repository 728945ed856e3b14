"""The CAN-ECB's durable tables: one SQLite file per bus, written by a thread of its own.

The event loop never touches the file. The CAN-ECB hands writes to ``Store.submit`` with a
callback; a writer thread commits everything queued so far in one transaction and then calls
back on the loop, with None or the error. The CAN-ECB announces an assignment or a binding
only after its callback said it is durable.

A file is used by one CAN-ECB at a time: ``Store`` holds an exclusive lock on ``FILE.lock``
and refuses to open a file another process holds. The file is open only while writes are
queued. If it was deleted or replaced, the writer writes the whole table into a new file at the
same path: at the next write, at the latest ``CHECK_EVERY`` seconds later (it looks while idle),
and before it stops; so a file lost while the CAN-ECB runs loses nothing it knew.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import os
import queue
import sqlite3
import threading
from collections.abc import Callable
from pathlib import Path

from ups._bindings import default_db, state_dir
from ups._errors import ConfigError

log = logging.getLogger("ups.can_ecb")

BUSY_TIMEOUT = 5.0  #: seconds a write waits for a lock that another program holds on the file
MAX_BATCH = 4096  #: writes committed in one transaction, at most
CHECK_EVERY = 1.0  #: seconds between two looks, while idle, whether the file is still there

#: One write: (table, key, value). table is "txnodes" (node id -> TxNode), "etags" (UID ->
#: etag) or "creators" (UID -> the node id that created its binding, for the quota); value None
#: deletes the row.
Write = tuple[str, int, int | None]
Done = Callable[[BaseException | None], None]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS txnodes (node_id TEXT PRIMARY KEY, txnode INTEGER UNIQUE NOT NULL);
CREATE TABLE IF NOT EXISTS etags (uid TEXT PRIMARY KEY, etag INTEGER UNIQUE NOT NULL);
CREATE TABLE IF NOT EXISTS creators (uid TEXT PRIMARY KEY, node_id TEXT NOT NULL);
"""
_COLUMNS = {
    "txnodes": ("node_id", "txnode"),
    "etags": ("uid", "etag"),
    "creators": ("uid", "node_id"),
}
_UNIQUE = {"txnodes", "etags"}  # tables whose values are unique too (a TxNode, an etag)
__all__ = ["Store", "default_db", "state_dir"]  # the state files' paths live in ups._bindings


class Store:
    """The tables of one bus, loaded at start and written in batches by a thread."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = _lock(self.path)
        try:
            db = self._connect()
            try:
                self.txnodes: dict[int, int] = _load(db, "txnodes")
                self.etags: dict[int, int] = _load(db, "etags")
                self.creators: dict[int, int] = _load(db, "creators")
            finally:
                db.close()
        except sqlite3.Error as exc:
            os.close(self._lock)
            raise ConfigError(f"cannot use the CAN-ECB database {self.path}: {exc}") from exc
        self._inode = _inode(self.path)
        self._db: sqlite3.Connection | None = None  # open while writes are queued
        #: what the file holds, as the writer thread knows it (to rewrite a deleted file)
        self._durable = {
            "txnodes": dict(self.txnodes), "etags": dict(self.etags),
            "creators": dict(self.creators),
        }  # fmt: skip
        self._queue: queue.SimpleQueue[tuple[list[Write], Done] | None] = queue.SimpleQueue()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self.batches = 0
        self.errors = 0
        self.last_error: str | None = None
        self._check_error: str | None = None  # the last error of a look at the file (logged)

    def start(self) -> None:
        """Start the writer; callbacks run on the calling (running) event loop."""
        if self._thread is None:
            self._loop = asyncio.get_running_loop()
            self._thread = threading.Thread(target=self._run, name="ups-ecb-store", daemon=True)
            self._thread.start()

    def submit(self, writes: list[Write], done: Done) -> None:
        """Make ``writes`` durable; ``done(None)`` once they are, ``done(error)`` if not."""
        self._queue.put((writes, done))

    def close(self) -> None:
        """Finish the writes already submitted, then let go of the lock."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=BUSY_TIMEOUT + 2)
            self._thread = None
        if self._lock >= 0:
            os.close(self._lock)
            self._lock = -1

    # --- the writer thread -----------------------------------------------------------------

    def _connect(self) -> sqlite3.Connection:
        self.path.parent.mkdir(parents=True, exist_ok=True)  # deleted with the file, maybe
        db = sqlite3.connect(str(self.path), timeout=BUSY_TIMEOUT, check_same_thread=False)
        db.executescript(_SCHEMA)
        return db

    def _run(self) -> None:
        while True:
            try:
                item = self._queue.get(timeout=CHECK_EVERY)
            except queue.Empty:
                self._check()
                continue
            if item is None:
                self._check()
                return
            batch = [item]
            while len(batch) < MAX_BATCH:
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is None:
                    self._queue.put(None)  # finish this batch, then stop
                    break
                batch.append(more)
            error = self._commit([w for writes, _ in batch for w in writes])
            for _, done in batch:
                self._call_back(done, error)
            if self._queue.empty():  # idle: hold no descriptor open for writing
                self._close_db()

    def _commit(self, writes: list[Write]) -> BaseException | None:
        """Write one batch. The file stays open while batches follow each other and is closed
        when none waits, so no descriptor stays open for writing while the CAN-ECB is idle
        (a disk can be remounted)."""
        try:
            inode = _inode(self.path)
            if self._db is None or inode != self._inode:
                self._close_db()
                self._db = self._connect()
            db = self._db
            lost = inode != self._inode  # deleted or replaced: write it all anew
            with db:
                if lost:
                    self._write_all(db)
                for table, key, value in writes:
                    key_col, value_col = _COLUMNS[table]
                    db.execute(f"DELETE FROM {table} WHERE {key_col} = ?", (f"{key:016x}",))
                    if value is not None:
                        if table in _UNIQUE:
                            db.execute(f"DELETE FROM {table} WHERE {value_col} = ?", (value,))
                        row = (f"{key:016x}", _column(table, value))
                        db.execute(f"INSERT INTO {table} VALUES (?, ?)", row)
            self._inode = _inode(self.path)
        except (sqlite3.Error, OSError) as exc:
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            self._close_db()  # open afresh next time: the disk may have come back
            return exc
        self.batches += 1
        self.last_error = None
        for table, key, value in writes:
            if value is None:
                self._durable[table].pop(key, None)
            else:
                self._durable[table][key] = value
        if lost:
            log.error("CAN-ECB database %s was deleted or replaced: written anew, with the "
                      "%d TxNodes and %d etags this CAN-ECB knows", self.path,
                      len(self._durable["txnodes"]), len(self._durable["etags"]))  # fmt: skip
        return None

    def _check(self) -> None:
        """Idle, or stopping: if the file was deleted or replaced, write it all anew now,
        rather than at the next write (which may never come)."""
        if _inode(self.path) != self._inode:
            error = self._commit([])  # kept in last_error (unhealthy), tried again next time
            self._close_db()
            if error is not None and self.last_error != self._check_error:
                log.error("CAN-ECB database %s was deleted or replaced, and cannot be written "
                          "anew: %s", self.path, error)  # fmt: skip
            self._check_error = self.last_error

    def _close_db(self) -> None:
        if self._db is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None

    def _write_all(self, db: sqlite3.Connection) -> None:
        for table in _COLUMNS:
            db.execute(f"DELETE FROM {table}")
            db.executemany(
                f"INSERT INTO {table} VALUES (?, ?)",
                [(f"{k:016x}", _column(table, v)) for k, v in self._durable[table].items()],
            )

    def _call_back(self, done: Done, error: BaseException | None) -> None:
        loop = self._loop
        assert loop is not None
        with contextlib.suppress(RuntimeError):  # the loop closed under us
            loop.call_soon_threadsafe(done, error)


def _load(db: sqlite3.Connection, table: str) -> dict[int, int]:
    rows = db.execute(f"SELECT * FROM {table}")
    return {int(k, 16): int(v, 16) if isinstance(v, str) else v for k, v in rows}


def _column(table: str, value: int) -> int | str:
    """A value as its column holds it: node ids (64 bits, beyond SQLite's integers) in hex."""
    return f"{value:016x}" if table == "creators" else value


def _inode(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _lock(path: Path) -> int:
    """Hold ``PATH.lock`` exclusively (through a descriptor open for reading only, so the disk
    can still be remounted), or fail naming the process that holds it."""
    lock_path = Path(f"{path}.lock")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock_path, os.O_RDONLY | os.O_CREAT, 0o644)
    except OSError as exc:
        raise ConfigError(f"cannot use the CAN-ECB database {path}: {exc}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = _lock_holder(os.fstat(fd).st_ino)
        os.close(fd)
        raise ConfigError(
            f"the CAN-ECB database {path} is in use by {holder}: one CAN-ECB per bus, and each "
            "bus its own --db"
        ) from None
    return fd


def _lock_holder(inode: int) -> str:
    """The process holding a flock on ``inode``, as /proc/locks says."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/locks").read_text().splitlines():
            fields = line.split()
            if len(fields) > 5 and fields[1] == "FLOCK" and fields[5].endswith(f":{inode}"):
                return f"process {fields[4]}"
    return "another process"
