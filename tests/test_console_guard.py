"""``ups console`` as a real process under the attacks of issue 32: a DNS-rebinding page posting
to a console that listens on every address, live streams that never read, requests whose
headers never end. Scaled down (a few connections, small receive buffers, a bounded number
of seconds); the full-size figures are in the issue's report, not asserted here."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import select
import socket
from collections.abc import Iterator

import aiohttp
import pytest

from ups.tools.console import MAX_PAGES_PER_CLIENT

from .procs import ROOT, Proc, start_tcp_broker

CATALOG = str(ROOT / "examples" / "robots.toml")
JSON = {"Content-Type": "application/json"}


@contextlib.contextmanager
def console(*options: str, listen: str = "0.0.0.0:0") -> Iterator[tuple[int, Proc, str]]:
    """A TCP-ECB and ``ups console --listen LISTEN``; yields the console's port, the process
    and the TCP-ECB's address."""
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("console", "--listen", listen, "--broker", address, "--catalog",
                      CATALOG, *options) as proc:  # fmt: skip
        line = proc.wait_for_line(r"console on http://")
        found = re.search(r":(\d+)\s*$", line)
        assert found is not None
        yield int(found.group(1)), proc, address


async def test_a_dns_rebinding_post_is_refused_when_the_console_listens_everywhere() -> None:
    """The reported attack: with --listen 0.0.0.0, a page of attacker.example (a name that now
    resolves to the console's address) posted, and it was published. The browser sends that
    name as Host, and the page's own origin as Origin (so the Origin check passed)."""
    with console() as (port, proc, address), Proc(
        "sub", "robot/max-speed", "--broker", address, "--json", "--count", "1", "--timeout",
        "60",
    ) as sub:  # fmt: skip
        sub.wait_for_line("subscribed to")
        url, evil = f"http://127.0.0.1:{port}", f"attacker.example:{port}"
        rebound = {"Host": evil, "Origin": f"http://{evil}", **JSON}
        async with aiohttp.ClientSession() as http:
            body = json.dumps({"channel": "robot/max-speed", "data": "limit=200"})
            reply = await http.post(f"{url}/publish", data=body, headers=rebound)
            assert reply.status == 421, await reply.text()
            reply = await http.get(f"{url}/snapshot", headers={"Host": evil})
            assert reply.status == 421  # nor can it read
            own = {"Host": f"127.0.0.1:{port}", "Origin": f"http://127.0.0.1:{port}", **JSON}
            body = json.dumps({"channel": "robot/max-speed", "data": "limit=30"})
            reply = await http.post(f"{url}/publish", data=body, headers=own)
            assert reply.status == 200, await reply.text()
        code, out = sub.finish(timeout=60)
        assert code == 0 and json.loads(out)["data"] == "001e"  # the first event: its own
        proc.wait_for_line(r"'attacker\.example:\d+' refused: not this console's name")


async def test_the_console_answers_addresses_and_the_names_it_was_given() -> None:
    """An IP address can be no attacker's page's name; localhost and the --allow-host names
    are the console's (compared without port, case or final dot); any other name is not."""
    with console("--allow-host", "robot.example") as (port, _, _):
        async with aiohttp.ClientSession() as http:
            for name, status in (
                (f"127.0.0.1:{port}", 200), (f"[::1]:{port}", 200), ("192.0.2.7:8470", 200),
                (f"localhost:{port}", 200), (f"robot.example:{port}", 200),
                ("ROBOT.example.", 200), (f"robot.example.attacker.example:{port}", 421),
                (f"attacker.example:{port}", 421), ("127.0.0.1.attacker.example", 421),
            ):  # fmt: skip
                reply = await http.get(f"http://127.0.0.1:{port}/snapshot",
                                       headers={"Host": name})  # fmt: skip
                assert reply.status == status, name


async def open_stream(port: int, source: str, rcvbuf: int | None = None) -> socket.socket:
    """A client at ``source`` asking for the live stream (GET /events) that reads nothing
    after the request is sent; ``rcvbuf``: its receive buffer (small: it fills at once)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.bind((source, 0))
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    await loop.sock_connect(sock, ("127.0.0.1", port))
    request = f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n"
    await loop.sock_sendall(sock, request.encode())
    return sock


async def first_line(sock: socket.socket) -> bytes:
    """The status line of the answer (this client reads)."""
    loop = asyncio.get_running_loop()
    data = b""
    async with asyncio.timeout(20):
        while b"\r\n" not in data:
            chunk = await loop.sock_recv(sock, 4096)
            assert chunk, "closed before answering"
            data += chunk
    return data.split(b"\r\n", 1)[0]


def hung_up(sock: socket.socket, seconds: float) -> bool:
    """Whether the console closed (reset) this connection within ``seconds``, without our
    reading a byte: poll() says so (POLLHUP, POLLERR, POLLRDHUP)."""
    poller = select.poll()
    poller.register(sock, select.POLLRDHUP | select.POLLHUP | select.POLLERR)
    events = poller.poll(seconds * 1000)
    return any(mask & (select.POLLRDHUP | select.POLLHUP | select.POLLERR) for _, mask in events)


@pytest.mark.timeout(240)
async def test_live_streams_are_bounded_per_client_and_dropped_when_they_stop_reading() -> None:
    """The reported attack: 32 live streams that never read held every slot (503 for
    everyone). Now a client has at most MAX_PAGES_PER_CLIENT (the next is 429) while another
    client is served; a stream whose reader stopped is reset once TCP shows its snapshots
    piling up (its receive buffer is made small here, so that comes in seconds); the page
    itself holds no stream and is served throughout. The streams' snapshots come every 0.1 s
    here (--snapshot-every; 0.5 by default), so that they pile up sooner."""
    with console("--snapshot-every", "0.1", listen="127.0.0.1:0") as (port, proc, _):
        hogs = [await open_stream(port, "127.0.0.1", rcvbuf=2048)
                for _ in range(MAX_PAGES_PER_CLIENT)]  # fmt: skip
        extra = await open_stream(port, "127.0.0.1")
        assert await first_line(extra) == b"HTTP/1.1 429 Too Many Requests"
        other = await open_stream(port, "127.0.0.2")  # another client
        assert await first_line(other) == b"HTTP/1.1 200 OK"
        async with aiohttp.ClientSession() as http:  # what the page asks, twice a second
            assert (await http.get(f"http://127.0.0.1:{port}/snapshot")).status == 200
        for hog in hogs:  # dropped, each within 90 s at most (seconds here)
            assert await asyncio.to_thread(hung_up, hog, 90), "a stream that never reads"
        proc.wait_for_line(r"live stream of 127\.0\.0\.1 dropped: \d+ bytes unread")
        again = await open_stream(port, "127.0.0.1")  # its slots are free again
        assert await first_line(again) == b"HTTP/1.1 200 OK"
        for sock in (*hogs, extra, other, again):
            sock.close()


async def test_a_request_must_arrive_whole_within_the_header_timeout() -> None:
    """The reported attack: slow connections (5,000 in the report) sending headers that never
    end stayed open. Here 40, each adding a byte whenever a second passes without the console
    closing it, for at most 30 s; every one is closed, and a whole request is served
    meanwhile. The header timeout is 3 s here (--header-timeout; 10 by default)."""
    with console("--header-timeout", "3", listen="127.0.0.1:0") as (port, proc, _):
        slow = [await asyncio.open_connection("127.0.0.1", port) for _ in range(40)]
        for _, writer in slow:
            writer.write(f"GET /snapshot HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nX-Slow: ".encode())

        async def trickle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> bool:
            """True once the console closed the connection; False if still open after 30 s."""
            try:
                for _ in range(30):
                    try:
                        async with asyncio.timeout(1.0):
                            return await reader.read(1) == b""
                    except TimeoutError:
                        writer.write(b"a")  # one more byte of a header that never ends
                        await writer.drain()
                return False
            except ConnectionError:
                return True
            finally:
                writer.close()

        closing = asyncio.gather(*(trickle(r, w) for r, w in slow))
        async with aiohttp.ClientSession() as http:
            assert (await http.get(f"http://127.0.0.1:{port}/snapshot")).status == 200
        assert all(await closing)
        proc.wait_for_line(r"closed: no whole request within 3 s")
