"""The floor: blocking TCP sockets, TCP_NODELAY, 8-byte messages without any framing."""

from __future__ import annotations

import socket
import time

from ups.benchmarks.peers import PAYLOAD_SIZE, STOP, Control, Link, SinkResult, seq
from ups.benchmarks.peers._common import Counter


def describe(link: Link) -> str:
    """A short note for the table."""
    return "blocking socket, one send/recv per message"


def _listen(link: Link) -> socket.socket:
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((link.host, link.ports[0]))
    srv.listen(1)
    return srv


def _accept(srv: socket.socket, timeout: float = 20.0) -> socket.socket:
    srv.settimeout(timeout)
    conn, _ = srv.accept()
    conn.settimeout(None)
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return conn


def _connect(link: Link) -> socket.socket:
    sock = socket.create_connection((link.host, link.ports[0]), timeout=10.0)
    sock.settimeout(None)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def _recv_exact(sock: socket.socket, view: memoryview) -> bool:
    """Fill ``view`` from ``sock``; False if the peer closed first."""
    got = 0
    while got < len(view):
        n = sock.recv_into(view[got:])
        if n == 0:
            return False
        got += n
    return True


def run_pong(link: Link, ctl: Control) -> None:
    """Echo 8-byte messages until STOP or EOF."""
    with _listen(link) as srv:
        ctl.ready()
        with _accept(srv) as conn:
            buf = bytearray(PAYLOAD_SIZE)
            view = memoryview(buf)
            while _recv_exact(conn, view):
                conn.sendall(buf)
                if buf == STOP:
                    return


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Ping-pong ``warmup + rounds`` messages; return the last ``rounds`` RTTs in seconds."""
    rtts: list[float] = []
    buf = bytearray(PAYLOAD_SIZE)
    view = memoryview(buf)
    clock = time.perf_counter
    with _connect(link) as sock:
        for i in range(warmup + rounds):
            msg = seq(i)
            t0 = clock()
            sock.sendall(msg)
            if not _recv_exact(sock, view) or buf != msg:
                raise RuntimeError(f"round {i}: bad or missing echo")
            rtts.append(clock() - t0)
        sock.sendall(STOP)
        _recv_exact(sock, view)
    return rtts[warmup:]


def run_sink(link: Link, ctl: Control, count: int, idle_timeout: float) -> SinkResult:
    """Count bytes / 8 until ``count`` messages, EOF, or idle timeout."""
    counter = Counter(count, idle_timeout)
    buf = bytearray(1 << 16)
    partial = 0
    with _listen(link) as srv:
        ctl.ready()
        with _accept(srv) as conn:
            while not counter.finished():
                conn.settimeout(max(counter.remaining(), 1e-3))
                try:
                    n = conn.recv_into(buf)
                except TimeoutError:
                    break
                if n == 0:
                    break
                whole, partial = divmod(partial + n, PAYLOAD_SIZE)
                if whole:
                    counter.add(whole)
    return counter.result()


def run_source(link: Link, ctl: Control, count: int) -> None:
    """Send ``count`` messages, one ``sendall`` each (blocks when the peer lags)."""
    with _connect(link) as sock:
        for i in range(count):
            sock.sendall(seq(i))
        ctl.wait_release()
