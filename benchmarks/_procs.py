"""The one harness every benchmark starts its processes with.

- :func:`process`: a daemon (a TCP-ECB, a router, mosquitto, ...) started with its output in a
  file, waited for until it logs a line matching ``ready`` (or accepts connections on an
  address), and stopped by its PID when the ``with`` block ends;
- :class:`Child`: a measuring process that prints JSON lines (its records) on stdout, may read
  commands on stdin, and whose stderr is kept for errors;
- :class:`Spawned`: a measuring role, a function run in a spawned interpreter, that talks over
  a pipe (``(kind, value)`` messages);
- :func:`cpu_hog`: one busy process per CPU, for measuring under load;
- :func:`wall_time`: how long a short command takes, start to exit;
- :func:`free_port`, :func:`free_ports`, :func:`set_affinity`.

Every wait has a timeout, and every process is ended by its own PID: SIGTERM, then SIGKILL.
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing
import os
import queue
import re
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parents[1]
START_TIMEOUT = 20.0  #: for a daemon to be ready
SETUP_TIMEOUT = 60.0  #: for a child's line or record
EXIT_GRACE = 10.0  #: for a process to exit by itself, then again after SIGTERM
_SPAWN = multiprocessing.get_context("spawn")  # a fresh interpreter: no state inherited


def free_ports(n: int, host: str = "127.0.0.1") -> tuple[int, ...]:
    """``n`` distinct TCP ports on ``host`` that were free a moment ago."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_STREAM) for _ in range(n)]
    try:
        for s in socks:
            s.bind((host, 0))
        return tuple(s.getsockname()[1] for s in socks)
    finally:
        for s in socks:
            s.close()


def free_port(host: str = "127.0.0.1") -> int:
    return free_ports(1, host)[0]


def set_affinity(pid: int, cpus: set[int]) -> None:
    """Move every thread of ``pid`` to ``cpus``."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(int(tid), cpus)


#: a busy loop that ends by itself after argv[1] seconds
_HOG = (
    "import sys, time\n"
    "end = time.monotonic() + float(sys.argv[1])\n"
    "while time.monotonic() < end: pass"
)


@contextlib.contextmanager
def cpu_hog(seconds: float, cpus: int | None = None) -> Iterator[list[int]]:
    """Hold every CPU (``cpus`` busy processes, default one per CPU, normal priority) for at
    most ``seconds``, or until the block ends; yields their PIDs."""
    count = cpus if cpus is not None else os.cpu_count() or 1
    hogs = [
        subprocess.Popen(["python3", "-c", _HOG, repr(seconds)], stdin=subprocess.DEVNULL)
        for _ in range(count)
    ]
    try:
        yield [h.pid for h in hogs]
    finally:
        for hog in hogs:
            _end(hog, EXIT_GRACE)


def _end(popen: subprocess.Popen[Any], grace: float) -> None:
    """SIGTERM, ``grace`` s, then SIGKILL: ``popen``'s own PID only."""
    if popen.poll() is None:
        popen.send_signal(signal.SIGTERM)
        try:
            popen.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            popen.kill()
            popen.wait(timeout=grace)


def wall_time(cmd: list[str], timeout: float = 30.0) -> float:
    """Seconds from starting ``cmd`` (output discarded) to its exit, which must be 0. The wait
    blocks in waitpid: ``subprocess.run(timeout=...)`` polls instead, sleeping 0.5, 1, 2 ... up
    to 50 ms between looks, so every figure it gives is rounded up to 31.5, 63.5, 113.5 ms ..."""
    started = time.perf_counter()
    with subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL) as popen:
        watchdog = threading.Timer(timeout, popen.kill)  # its own PID only
        watchdog.start()
        code = popen.wait()
        elapsed = time.perf_counter() - started
        watchdog.cancel()
    if code != 0:
        raise subprocess.CalledProcessError(code, cmd)
    return elapsed


@dataclass
class Started:
    """A daemon :func:`process` started: its process, and what its ready line matched."""

    popen: subprocess.Popen[bytes]
    found: re.Match[str] | None

    @property
    def pid(self) -> int:
        return self.popen.pid


@contextlib.contextmanager
def process(
    cmd: list[str],
    ready: str | tuple[str, int],
    *,
    pin: int | None = None,
    timeout: float = START_TIMEOUT,
) -> Iterator[Started]:
    """``cmd`` started (pinned to CPU ``pin``, with its threads) with its output in a file;
    yielded once its output matches the regex ``ready``, or once it accepts connections on the
    address ``ready``; stopped when the block ends. RuntimeError, with the end of its output,
    if it exits or is not ready within ``timeout`` s."""
    with tempfile.TemporaryDirectory(prefix="ups-bench-") as tmp:
        log = Path(tmp, "log")
        with log.open("wb") as out:
            popen = subprocess.Popen(
                cmd, cwd=ROOT, stdin=subprocess.DEVNULL, stdout=out, stderr=out
            )  # fmt: skip
        try:
            if pin is not None:
                set_affinity(popen.pid, {pin})
            deadline = time.monotonic() + timeout
            while True:
                found = _ready(ready, log)
                if found:
                    break
                if popen.poll() is not None or time.monotonic() > deadline:
                    why = "exited" if popen.poll() is not None else f"not ready in {timeout} s"
                    tail = log.read_text(errors="replace")[-500:]
                    raise RuntimeError(f"{' '.join(cmd[:4])}: {why}: {tail}")
                time.sleep(0.02)
            yield Started(popen, found if isinstance(found, re.Match) else None)
        finally:
            _end(popen, 5.0)


def _ready(ready: str | tuple[str, int], log: Path) -> re.Match[str] | bool | None:
    if isinstance(ready, str):
        return re.search(ready, log.read_text(errors="replace"))
    try:
        with socket.create_connection(ready, timeout=1.0):
            return True
    except OSError:
        return False


class Child:
    """A measuring process: ``argv`` started with pipes; its stdout's JSON lines go to
    ``records`` (None once it ended; other lines are skipped), its stderr lines to ``stderr``.
    ``label`` names it in errors."""

    def __init__(self, argv: list[str], label: str) -> None:
        self.label = label
        self.popen = subprocess.Popen(
            argv, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True, bufsize=1,
        )  # fmt: skip
        self.records: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self.stderr: list[str] = []
        self._err: queue.Queue[str | None] = queue.Queue()
        assert self.popen.stdout is not None and self.popen.stderr is not None
        self._threads = [
            threading.Thread(target=self._read_out, args=(self.popen.stdout,), daemon=True),
            threading.Thread(target=self._read_err, args=(self.popen.stderr,), daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def _read_out(self, stream: IO[str]) -> None:
        for line in stream:
            with contextlib.suppress(ValueError):
                record = json.loads(line)
                if isinstance(record, dict):
                    self.records.put(record)
        self.records.put(None)

    def _read_err(self, stream: IO[str]) -> None:
        for line in stream:
            self.stderr.append(line)
            self._err.put(line)
        self._err.put(None)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def wait_stderr(self, pattern: str, timeout: float = SETUP_TIMEOUT) -> re.Match[str]:
        """The first stderr line (from now on) matching ``pattern``."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self._err.get(timeout=left)
            except queue.Empty:
                break
            if line is None:
                raise RuntimeError(f"{self.label} ended: {self.tail()}")
            if found := regex.search(line):
                return found
        raise RuntimeError(f"{self.label}: no {pattern!r} within {timeout} s: {self.tail()}")

    def event(self, timeout: float) -> dict[str, Any]:
        """The next record; RuntimeError if the child ended, reported an error, or printed
        none within ``timeout`` s."""
        try:
            record = self.records.get(timeout=timeout)
        except queue.Empty:
            raise RuntimeError(f"{self.label}: nothing within {timeout} s: {self.tail()}") from None
        if record is None:
            self.records.put(None)  # it stays ended
            raise RuntimeError(f"{self.label} ended: {self.tail()}")
        if record.get("event") == "error":
            raise RuntimeError(f"{self.label}: {record['error']}")
        return record

    def send(self, line: str) -> None:
        """A command line on the child's stdin (ignored if it is gone)."""
        assert self.popen.stdin is not None
        with contextlib.suppress(BrokenPipeError, OSError):
            self.popen.stdin.write(line + "\n")
            self.popen.stdin.flush()

    def close_stdin(self) -> None:
        """End of input: a child that reads commands takes it as the signal to leave."""
        if self.popen.stdin is not None:
            with contextlib.suppress(OSError):
                self.popen.stdin.close()

    def tail(self, lines: int = 15) -> str:
        time.sleep(0.2)  # its last words may still be in the pipe
        return "".join(self.stderr[-lines:]).strip() or "(no stderr)"

    def finish(self, timeout: float = EXIT_GRACE) -> int:
        """Wait ``timeout`` s for the child to exit by itself, then stop it; its exit code."""
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.popen.wait(timeout=timeout)
        self.stop()  # at once if it is still there; else only its pipes and readers
        return self.popen.returncode

    def stop(self) -> None:
        """SIGTERM, then SIGKILL (``ip netns exec`` execs its command: the PID is the child's)."""
        _end(self.popen, EXIT_GRACE)
        self.close_stdin()
        for thread in self._threads:
            thread.join(timeout=2)


class Spawned:
    """``target(*args, conn)`` in a spawned process, named ``name``: it sends ``(kind, value)``
    messages on ``conn`` and may be sent commands. A target that catches its own failure sends
    ``("error", traceback)`` (the peers' ``run_role`` does); one that dies shows as exited."""

    def __init__(self, target: Callable[..., None], args: tuple[Any, ...], name: str) -> None:
        self.conn, theirs = _SPAWN.Pipe()
        self.proc: BaseProcess = _SPAWN.Process(
            target=target, args=(*args, theirs), name=name, daemon=True
        )
        self.proc.start()
        theirs.close()

    def expect(self, kind: str, timeout: float) -> Any:
        """The value of the child's next message, which must be a ``kind``; TimeoutError or
        RuntimeError (with its traceback when it failed) otherwise."""
        name = self.proc.name
        if not self.conn.poll(timeout):
            raise TimeoutError(f"{name}: no {kind} within {timeout:.0f} s")
        try:
            got, value = self.conn.recv()
        except EOFError:
            raise RuntimeError(f"{name}: exited (code {self.proc.exitcode})") from None
        if got == "error":  # value: the child's traceback; its last line says what failed
            raise RuntimeError(f"{name}: {value.strip().splitlines()[-1]}\n{value}")
        if got != kind:
            raise RuntimeError(f"{name}: expected {kind}, got {got}")
        return value

    def ask(self, command: Any, kind: str, timeout: float = SETUP_TIMEOUT) -> Any:
        """Send ``command``; the answer's value (see :meth:`expect`)."""
        self.send(command)
        return self.expect(kind, timeout)

    def send(self, message: Any) -> None:
        with contextlib.suppress(OSError):  # it is gone: expect() says so
            self.conn.send(message)

    def stop(self, grace: float = EXIT_GRACE) -> None:
        """Give the child ``grace`` seconds to end, then kill it by its PID."""
        self.proc.join(grace)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(grace)
        self.conn.close()
