"""paho-mqtt 2.x, QoS 0, through a mosquitto broker that the harness starts per measurement.

The broker is a child process (``mosquitto -c <generated config>``) listening on
``127.0.0.1:ports[0]`` only, anonymous, no persistence, TCP_NODELAY on its client sockets;
the clients set TCP_NODELAY too (paho does not). For round trips the broker is pinned to
the same CPU as the two clients. It is stopped by PID afterwards.

``link.options["max_queued_messages"]``: mosquitto's per-client queue limit. mosquitto
drops QoS 0 messages for a subscriber whose queue is at the limit (default 1000), so a
publisher faster than the subscriber loses messages; 0 means no limit (and no loss).
A paho client drives its own network loop here (``Client.loop``) in the measuring thread.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ups.benchmarks._procs import process
from ups.benchmarks.peers import STOP, Control, Link, SinkResult, seq
from ups.benchmarks.peers._common import Counter

PING, PONG, DATA = "bench/ping", "bench/pong", "bench/data"
SETUP_TIMEOUT = 10.0
MOSQUITTO_DEFAULT_QUEUE = 1000


def _mosquitto() -> str | None:
    found = shutil.which("mosquitto")
    if found:
        return found
    return "/usr/sbin/mosquitto" if os.access("/usr/sbin/mosquitto", os.X_OK) else None


def missing(link: Link) -> str | None:
    """paho-mqtt 2.x or the mosquitto binary, if either is not installed."""
    if importlib.util.find_spec("paho") is None:
        return "paho-mqtt is not installed (scripts/bench-setup)"
    if int(importlib.metadata.version("paho-mqtt").split(".")[0]) < 2:
        return "paho-mqtt < 2"
    if _mosquitto() is None:
        return "mosquitto is not installed (scripts/bench-setup)"
    return None


def describe(link: Link) -> str:
    """Versions, and the broker's queue limit."""
    limit = link.options.get("max_queued_messages")
    queue = "no queue limit" if limit == 0 else f"queue limit {limit or MOSQUITTO_DEFAULT_QUEUE}"
    version = subprocess.run([_mosquitto() or "mosquitto", "-h"], capture_output=True,
                             text=True, timeout=10).stdout.split("\n", 1)[0]  # fmt: skip
    return f"paho {importlib.metadata.version('paho-mqtt')}, {version.strip()}, {queue}"


def _config(link: Link) -> str:
    lines = [f"listener {link.ports[0]} {link.host}", "allow_anonymous true",
             "persistence false", "set_tcp_nodelay true", "log_dest stderr"]  # fmt: skip
    limit = link.options.get("max_queued_messages")
    if limit is not None:
        lines += [f"max_queued_messages {limit}", "max_queued_bytes 0"]
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def service(link: Link, pin: int | None) -> Iterator[None]:
    """A mosquitto child process on ``link.ports[0]`` (pinned to ``pin``), stopped after."""
    with tempfile.TemporaryDirectory(prefix="bench-mosquitto-") as tmp:
        conf = Path(tmp, "mosquitto.conf")
        conf.write_text(_config(link))
        cmd = [_mosquitto() or "mosquitto", "-c", str(conf)]
        with process(cmd, (link.host, link.ports[0]), pin=pin, timeout=SETUP_TIMEOUT):
            yield


def _client(link: Link, on_message: Callable[[Any], None] | None = None) -> Any:
    """A connected paho client (its own loop, driven by the caller), TCP_NODELAY on."""
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    client = mqtt.Client(CallbackAPIVersion.VERSION2, protocol=mqtt.MQTTv311)
    state = {"connected": False}

    def on_connect(_c: Any, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if reason.is_failure:
            raise RuntimeError(f"connect refused: {reason}")
        state["connected"] = True

    def on_socket_open(_c: Any, _u: Any, sock: Any) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    client.on_connect = on_connect
    client.on_socket_open = on_socket_open
    if on_message is not None:
        client.on_message = lambda _c, _u, msg: on_message(msg)
    client.connect(link.host, link.ports[0], keepalive=120)
    _loop_until(client, lambda: state["connected"], SETUP_TIMEOUT)
    return client


def _loop_until(client: Any, condition: Callable[[], bool], timeout: float) -> None:
    """Run the client's network loop until ``condition()``; TimeoutError after ``timeout``."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"MQTT: gave up after {timeout} s")
        rc = client.loop(0.1)
        if rc != 0:
            raise RuntimeError(f"MQTT loop: error {rc}")


def _subscribe(client: Any, topic: str) -> None:
    """Subscribe at QoS 0 and wait for the SUBACK."""
    acked: list[int] = []
    client.on_subscribe = lambda _c, _u, mid, _r, _p: acked.append(mid)
    _, mid = client.subscribe(topic, qos=0)
    _loop_until(client, lambda: mid in acked, SETUP_TIMEOUT)


def run_pong(link: Link, ctl: Control) -> None:
    """Echo PING to PONG until STOP.

    The echo is published after ``Client.loop`` returns, not inside ``on_message``: from a
    callback paho only queues the packet, and it goes out one ``select`` later.
    """
    received: list[bytes] = []
    client = _client(link, lambda msg: received.append(msg.payload))
    _subscribe(client, PING)
    ctl.ready()
    deadline = time.monotonic() + 600.0
    while time.monotonic() < deadline:
        _loop_until(client, lambda: bool(received), 600.0)
        for payload in received:
            client.publish(PONG, payload, qos=0)
        if STOP in received:
            break
        received.clear()
    _loop_until(client, lambda: not client.want_write(), SETUP_TIMEOUT)
    client.disconnect()


def run_ping(link: Link, ctl: Control, warmup: int, rounds: int) -> list[float]:
    """Publish on PING, wait for the echo on PONG; the last ``rounds`` RTTs in seconds."""
    replies: list[bytes] = []
    client = _client(link, lambda msg: replies.append(msg.payload))
    _subscribe(client, PONG)
    rtts: list[float] = []
    clock = time.perf_counter
    for i in range(warmup + rounds):
        msg = seq(i)
        t0 = clock()
        client.publish(PING, msg, qos=0)
        _loop_until(client, lambda: bool(replies), SETUP_TIMEOUT)
        rtts.append(clock() - t0)
        if replies.pop() != msg or replies:
            raise RuntimeError(f"round {i}: wrong or extra echo")
    client.publish(PING, STOP, qos=0)
    _loop_until(client, lambda: bool(replies), SETUP_TIMEOUT)
    client.disconnect()
    return rtts[warmup:]


def run_sink(link: Link, ctl: Control, count: int, idle_timeout: float) -> SinkResult:
    """Subscribe to DATA and count until ``count`` arrived or nothing came for a while."""
    client = _client(link, lambda _msg: counter.add())  # nothing arrives before SUBACK
    _subscribe(client, DATA)
    counter = Counter(count, idle_timeout)
    ctl.ready()
    while not counter.finished():
        client.loop(min(0.1, max(counter.remaining(), 1e-3)))
    client.disconnect()
    return counter.result()


def run_source(link: Link, ctl: Control, count: int) -> None:
    """Publish ``count`` messages on DATA, then run the loop until paho has written them all."""
    client = _client(link)
    info = None
    for i in range(count):
        info = client.publish(DATA, seq(i), qos=0)
    _loop_until(client, lambda: info is None or info.is_published(), 120.0)
    ctl.wait_release()
    client.disconnect()
