"""``ups console`` with real processes and a real headless Chromium (Debian's), driven over its
DevTools protocol: the page shows live channels, decoded values and nodes, and its form
publishes an event that a ``ups sub`` process receives."""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import subprocess
import tempfile
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import aiohttp
import pytest

from .procs import ROOT, Proc, start_tcp_broker

CATALOG = str(ROOT / "examples" / "robots.toml")
JSON = {"Content-Type": "application/json"}


def chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        if os.environ.get("UPS_REQUIRE_CHROMIUM") == "1":
            pytest.fail("no chromium: scripts/setup --test installs it (as root)")
        pytest.skip("no chromium (scripts/setup --test installs Debian's, as root)")
    return found


class Page:
    """One page of a headless Chromium, evaluated over the DevTools protocol."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self._ws = ws
        self._ids = 0

    async def eval(self, expression: str) -> Any:
        self._ids += 1
        await self._ws.send_json({"id": self._ids, "method": "Runtime.evaluate",
                                  "params": {"expression": expression, "returnByValue": True,
                                             "awaitPromise": True}})  # fmt: skip
        while True:
            reply = await self._ws.receive_json(timeout=20)
            if reply.get("id") == self._ids:
                return reply["result"]["result"].get("value")

    async def until(self, expression: str, timeout: float = 20.0) -> Any:
        """The value of ``expression`` once it is truthy (evaluated every 0.1 s)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not (value := await self.eval(expression)):
            assert loop.time() < deadline, f"never true in the page: {expression}"
            await asyncio.sleep(0.1)
        return value


@asynccontextmanager
async def browser(url: str) -> AsyncIterator[Page]:
    profile = tempfile.mkdtemp(prefix="ups-chromium-")
    proc = await asyncio.create_subprocess_exec(
        chromium(), "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
        f"--user-data-dir={profile}", "--remote-debugging-port=0", url,
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        assert proc.stderr is not None
        port = None
        async for raw in proc.stderr:  # "DevTools listening on ws://127.0.0.1:PORT/devtools/..."
            found = re.search(r"DevTools listening on ws://127\.0\.0\.1:(\d+)/", raw.decode())
            if found:
                port = int(found.group(1))
                break
        assert port is not None, "chromium did not start its DevTools server"
        async with aiohttp.ClientSession() as http:
            targets = await (await http.get(f"http://127.0.0.1:{port}/json/list")).json()
            page = next(t for t in targets if t["type"] == "page")
            async with http.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
                yield Page(ws)
    finally:
        proc.terminate()
        try:
            await asyncio.wait_for(proc.wait(), 10)
        except TimeoutError:
            proc.kill()
            await proc.wait()
        shutil.rmtree(profile, ignore_errors=True)


async def test_the_console_shows_the_network_live_and_publishes_from_its_form() -> None:
    chromium()
    broker, address = start_tcp_broker("--recovery", "0")
    with (
        broker,
        Proc(
            "pub",
            "robot/speed",
            "speed=42",
            "--broker",
            address,
            "--catalog",
            CATALOG,
            "--count",
            "100000",
            "--rate",
            "50",
        ),  # fmt: skip
        Proc(
            "sub",
            "robot/max-speed",
            "--broker",
            address,
            "--count",
            "1",
            "--json",
            "--timeout",
            "60",
        ) as sub,  # fmt: skip
        Proc(
            "console", "--listen", "127.0.0.1:0", "--broker", address, "--catalog", CATALOG
        ) as console,  # fmt: skip
    ):
        sub.wait_for_line("subscribed to")
        line = console.wait_for_line(r"console on http://127\.0\.0\.1:\d+")
        url = line.split("console on ")[1].strip()
        async with browser(f"{url}/#robot/speed") as page:
            rows = await page.until(
                "document.querySelector('#channels tbody').innerText.includes('speed=42 cm/s')"
                " && document.querySelector('#channels tbody').innerText"
            )
            assert "robot/speed" in rows and "robot/max-speed" in rows  # the sub's channel too
            nodes = await page.until("document.querySelector('#nodes tbody').innerText")
            assert "ups-pub" in nodes and "ups-sub" in nodes
            assert await page.until(  # the chosen channel is plotted
                "document.getElementById('plotted').textContent === 'robot/speed'"
            )
            await page.eval(
                "document.getElementById('pub-channel').value = 'robot/max-speed';"
                "document.getElementById('pub-data').value = 'limit=30';"
                "document.querySelector('#publish button').click(); true"
            )
            answer = await page.until("document.getElementById('answer').textContent")
            assert answer == "published 001e on robot/max-speed"
            await page.eval(
                "document.getElementById('pub-data').value = 'limit=x';"
                "document.querySelector('#publish button').click(); true"
            )
            error = await page.until(
                "document.getElementById('answer').className === 'error' &&"
                " document.getElementById('answer').textContent"
            )
            assert "limit='x'" in error
        code, out = sub.finish()
        assert code == 0 and json.loads(out)["data"] == "001e"


async def test_the_console_answers_bad_requests_with_a_message() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("console", "--listen", "127.0.0.1:0", "--broker", address) as console:
        url = console.wait_for_line(r"console on http://").split("console on ")[1].strip()
        async with aiohttp.ClientSession() as http:
            for body, status, says in [
                ("nope", 400, "Expecting value"),
                ('{"data": "01"}', 400, "missing 'channel'"),
                ('{"channel": "0xzz", "data": "01"}', 400, "bad channel UID"),
                ('{"channel": "a", "data": "zz"}', 400, "not hex digits"),
                ('{"channel": "a", "data": "v=1"}', 400, "the catalog has no layout of a"),
                ("[1]", 400, "must be a JSON object"),
            ]:
                reply = await http.post(f"{url}/publish", data=body, headers=JSON)
                assert reply.status == status and says in (await reply.json())["error"]
            # another web site's page cannot publish, nor read it under another name
            evil = {"Origin": "http://evil.example", **JSON}
            reply = await http.post(f"{url}/publish", data='{"channel": "a"}', headers=evil)
            assert reply.status == 403
            reply = await http.post(f"{url}/publish", data='{"channel": "a", "data": "01"}',
                                    headers={"Content-Type": "text/plain"})  # fmt: skip
            assert reply.status == 415  # what a form on another site can send without asking
            reply = await http.get(f"{url}/snapshot", headers={"Host": "evil.example:80"})
            assert reply.status == 421  # DNS rebinding
            snapshot = await (await http.get(f"{url}/snapshot")).json()
            assert snapshot["network"] == "tcp" and snapshot["source"] == address


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (("console", "--listen", "127.0.0.1:http", "--broker", "127.0.0.1:1"), "HOST:PORT"),
        (
            ("console", "--broker", "127.0.0.1:1", "--catalog", "/nonexistent.toml"),
            "cannot read the catalog",
        ),
    ],
)
def test_console_bad_input_is_one_line_and_exit_2(args: tuple[str, ...], says: str) -> None:
    proc = Proc(*args)
    code, _ = proc.finish()
    assert code == 2 and len(proc.stderr_lines) == 1 and says in proc.stderr_lines[0]


def test_a_console_port_in_use_is_one_line_and_exit_2() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("console", "--listen", "127.0.0.1:0", "--broker", address) as first:
        url = first.wait_for_line(r"console on http://").split("console on http://")[1].strip()
        second = Proc("console", "--listen", url, "--broker", address)
        code, _ = second.finish()
        assert code == 2 and len(second.stderr_lines) == 1, second.stderr_lines
        assert "in use" in second.stderr_lines[0]


async def test_the_console_stops_at_once_with_pages_open() -> None:
    broker, address = start_tcp_broker("--recovery", "0")
    with broker, Proc("console", "--listen", "127.0.0.1:0", "--broker", address) as console:
        url = console.wait_for_line(r"console on http://").split("console on ")[1].strip()
        async with aiohttp.ClientSession() as http:
            page = await http.get(f"{url}/events")  # a page following the stream
            assert (await page.content.readline()).startswith(b"data: ")
            loop = asyncio.get_running_loop()
            began = loop.time()
            code = await asyncio.to_thread(console.stop)  # SIGTERM, SIGKILL after 10 s
            assert code == 0 and loop.time() - began < 5


async def test_the_console_shows_jaus_components_and_the_ocus_connected() -> None:
    """A `ups jaus` node on the TCP-ECB, an OCU that took control: the page lists the
    component, its state and controller, and the OCU with its framing and address."""
    chromium()
    broker, address = start_tcp_broker("--recovery", "0")
    mapping = str(ROOT / "examples" / "robot.jaus.toml")
    with broker, Proc("jaus", "--listen", "127.0.0.1:0", "--id", "7.1.1", "--map", mapping,
                      "--broker", address) as component:  # fmt: skip
        line = component.wait_for_line(r"JAUS component 7\.1\.1 on")
        target = line.split(" on ")[1].split()[0]
        with Proc("jaus-ocu", "--target", target, "--id", "200.1.1", "--framing", "ra33",
                  "control", "request") as ocu:  # fmt: skip
            assert ocu.finish()[0] == 0
        with Proc("console", "--listen", "127.0.0.1:0", "--broker", address) as console:
            url = console.wait_for_line(r"console on http://").split("console on ")[1].strip()
            async with browser(url) as page:
                rows = await page.until(
                    "document.querySelector('#jaus tbody').innerText.includes('200.1.1') &&"
                    " document.querySelector('#jaus tbody').innerText"
                )
    assert "7.1.1" in rows and "RA 3.3" in rows and "127.0.0.1:" in rows
    assert "STANDBY" in rows  # the OCU took control, did not resume (it lapses after 5 s)
