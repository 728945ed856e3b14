"""Run ``ups`` commands as real processes: wait for their log lines, never leak them."""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path
from types import TracebackType

import pytest

ROOT = Path(__file__).resolve().parent.parent


class Proc:
    """A child process whose stderr lines are collected as they come."""

    def __init__(
        self,
        *args: str,
        prefix: tuple[str, ...] = (),
        env: dict[str, str] | None = None,
        cwd: Path = ROOT,
        shell: str | None = None,
        exact_env: bool = False,
        stdout: Path | None = None,
    ) -> None:
        """``ups ARGS...``; ``prefix`` runs it under another command (say ``unshare``), ``env``
        adds to the environment. ``shell``: a command line that bash runs instead, as a person
        types it; ``exact_env``: ``env`` is the whole environment. ``stdout``: a file that takes
        its output instead of a pipe that this process reads (a command that prints a lot then
        never waits for this process to read it; ``stdout_lines`` has its lines once it has
        finished)."""
        self.args = args or (shell or "",)
        self._stdout_file = stdout
        command = ["bash", "-c", shell] if shell is not None else [sys.executable, "-m", "upscli"]
        if exact_env:
            environment = env
        else:
            # faulthandler: a process that does not exit in time is made to say where it is
            environment = {**os.environ, "PYTHONFAULTHANDLER": "1"}
            if env is not None:
                environment.update({"PYTHONPATH": str(ROOT), **env})
        with contextlib.ExitStack() as files:
            out = files.enter_context(stdout.open("w")) if stdout else subprocess.PIPE
            self.popen = subprocess.Popen(
                [*prefix, *command, *args],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.PIPE,
                text=True,
                cwd=cwd,
                env=environment,
            )
        self.stderr_lines: list[str] = []
        self.stdout_lines: list[str] = []
        self._stdout_grew = threading.Condition()
        self._stdout_ended = False
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._out: queue.Queue[str | None] = queue.Queue()
        self._readers = [threading.Thread(target=self._read, daemon=True)]
        if stdout is None:
            self._readers.append(threading.Thread(target=self._read_stdout, daemon=True))
        for reader in self._readers:
            reader.start()

    def _read_stdout(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            with self._stdout_grew:
                self.stdout_lines.append(line)
                self._stdout_grew.notify_all()
            self._out.put(line)
        self._out.put(None)
        with self._stdout_grew:
            self._stdout_ended = True  # whoever waits for more lines can stop
            self._stdout_grew.notify_all()

    def wait_for_stdout(self, count: int, timeout: float = 20.0) -> list[str]:
        """Block until ``count`` lines came on stdout; fail if the process ends first."""
        with self._stdout_grew:
            if (
                not self._stdout_grew.wait_for(
                    lambda: len(self.stdout_lines) >= count or self._stdout_ended,
                    timeout,
                )
                or len(self.stdout_lines) < count
            ):
                raise AssertionError(
                    f"{self.args[0]}: {len(self.stdout_lines)} of {count} lines on stdout"
                )
            return list(self.stdout_lines)

    def _read(self) -> None:
        assert self.popen.stderr is not None
        for line in self.popen.stderr:
            self.stderr_lines.append(line)
            self._lines.put(line)
        self._lines.put(None)

    def wait_for_line(self, pattern: str, timeout: float = 20.0, *, stdout: bool = False) -> str:
        """Block until a stderr line (with ``stdout``, a stdout line) matches ``pattern``; fail
        if the process ends first."""
        regex = re.compile(pattern)
        lines = self._out if stdout else self._lines
        while True:
            try:
                line = lines.get(timeout=timeout)
            except queue.Empty:
                raise AssertionError(f"{self.args[0]}: no line matching {pattern!r}") from None
            if line is None:
                raise AssertionError(
                    f"{self.args[0]} ended before {pattern!r}:\n{''.join(self.stderr_lines)}"
                )
            if regex.search(line):
                return line

    def finish(self, timeout: float = 20.0) -> tuple[int, str]:
        """Wait for the process to exit by itself; return its exit code and stdout."""
        try:
            self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"{self.args[0]} did not exit within {timeout} s; where it was:\n" + self._where()
            ) from None
        for reader in self._readers:
            reader.join(timeout=5)
        if self._stdout_file is not None:
            self.stdout_lines = self._stdout_file.read_text().splitlines(keepends=True)
        return self.popen.returncode, "".join(self.stdout_lines)

    def kill(self) -> None:
        """SIGKILL: the process gets no chance to tidy up."""
        self.popen.kill()
        self.popen.wait()

    def interrupt(self) -> None:
        """SIGINT: what Ctrl-C in its terminal sends."""
        self.popen.send_signal(signal.SIGINT)

    def pause(self) -> None:
        self.popen.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        self.popen.send_signal(signal.SIGCONT)

    def _where(self) -> str:
        """SIGABRT a process that hangs: faulthandler (PYTHONFAULTHANDLER) prints every
        thread's stack on stderr; the end of its stderr, once it is gone."""
        self.popen.send_signal(signal.SIGCONT)
        self.popen.send_signal(signal.SIGABRT)
        try:
            self.popen.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.stop()
        for reader in self._readers:
            reader.join(timeout=5)
        return "".join(self.stderr_lines[-80:])

    def stop(self) -> int:
        """SIGTERM, then SIGKILL if it does not exit within 10 s; returns the exit code."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGCONT)  # a paused process could not handle SIGTERM
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
        for reader in self._readers:
            reader.join(timeout=5)
        return self.popen.returncode

    def __enter__(self) -> Proc:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()


def start_tcp_broker(*options: str, port: int = 0) -> tuple[Proc, str]:
    """``ups broker`` on loopback (any free port unless told); returns it and its HOST:PORT."""
    broker = Proc("broker", "--listen", f"127.0.0.1:{port}", *options)
    try:
        line = broker.wait_for_line(r"TCP-ECB on 127\.0\.0\.1:\d+")
    except BaseException:
        broker.stop()
        raise
    found = re.search(r"TCP-ECB on (127\.0\.0\.1:\d+)", line)
    assert found is not None
    return broker, found.group(1)


def private_network() -> None:
    """Go on only inside a private network namespace with no way out (scripts/netns-run): skip,
    or fail under UPS_REQUIRE_NETNS=1, unless there is no default route, i.e. only loopback
    exists. For multicast, which must never leave the machine, and for fixed ports."""
    routes = subprocess.run(
        ["ip", "route", "show", "default"], capture_output=True, text=True, check=False
    )
    if routes.returncode != 0 or routes.stdout.strip() or os.environ.get("UPS_IN_NETNS") != "1":
        reason = "needs a private network namespace: run through scripts/netns-run"
        if os.environ.get("UPS_REQUIRE_NETNS") == "1":
            pytest.fail(reason)
        pytest.skip(reason)


def private_multicast_bus() -> str:
    """A udp_multicast bus spec on a free port, only inside a namespace with no way out."""
    private_network()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"udp_multicast:239.74.163.2,port={port}"


def vcan_bus() -> str:
    """SocketCAN vcan0, which exists inside scripts/uml-run (skip, or fail there, without it)."""
    if not Path("/sys/class/net/vcan0").exists():
        reason = "no SocketCAN vcan0 here (run through scripts/uml-run)"
        if os.environ.get("UPS_REQUIRE_SOCKETCAN") == "1":
            pytest.fail(reason)
        pytest.skip(reason)
    return "socketcan:vcan0"


def sanitizer_env() -> dict[str, str]:
    """The environment a Python process needs to load the ASan+UBSan build of libups: the ASan
    runtime first, and sanitizer errors as exit codes (99, 98). Python's own allocations are no
    leaks of the library's: leaks are not checked."""
    libasan = subprocess.run(
        ["cc", "-print-file-name=libasan.so"], capture_output=True, text=True, check=True
    ).stdout.strip()
    return {
        "LD_PRELOAD": libasan,
        "ASAN_OPTIONS": "detect_leaks=0:abort_on_error=0:exitcode=99",
        "UBSAN_OPTIONS": "halt_on_error=1:print_stacktrace=1:exitcode=98",
    }
