"""The demo robot as separate processes (``ups demo --processes --can BUS``), for ``ups
monitor``, ``ups console``, ``ups ls`` and ``ups record`` to watch from other shells.

Needs a bus that processes share: SocketCAN (``socketcan:vcan0``), or udp_multicast inside a
private network namespace (``scripts/netns-run``). Starts a TCP-ECB, a gateway that hosts the
bus's CAN-ECB, the four CAN parts and the operator station, each one process
(``python -m ups.examples.robots PART``), prints what each part says, and stops them all (by PID)
on Ctrl-C, SIGTERM or after ``--duration``.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import sys
from pathlib import Path

from ups import UpsError

from .robots import PARTS, first_in_a_shell

ROOT = Path(__file__).resolve().parent.parent
CATALOG = Path(__file__).resolve().parent / "robots.toml"
START_TIMEOUT = 30.0  #: seconds for the TCP-ECB and the gateway to say they are up


async def run_fleet(bus: str, listen: str, duration: float | None) -> int:
    children: list[asyncio.subprocess.Process] = []
    pumps: list[asyncio.Task[None]] = []
    seen: set[str] = set()

    async def spawn(name: str, *args: str, ready: str | None = None) -> None:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, *args, cwd=ROOT, stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        children.append(proc)
        up = asyncio.get_running_loop().create_future()
        pumps.append(asyncio.create_task(_pump(name, proc, ready, up, seen)))
        if ready is None:
            return
        try:
            await asyncio.wait_for(asyncio.shield(up), START_TIMEOUT)
        except TimeoutError:
            raise UpsError(f"{name} did not start within {START_TIMEOUT:.0f} s") from None

    try:
        await spawn("broker", "-m", "upscli", "broker", "--listen", listen,
                    "--recovery", "0", ready="TCP-ECB on")  # fmt: skip
        await spawn("gateway", "-m", "upscli", "gateway", "--can", bus, "--broker", listen,
                    "--node-id", "0x0d3e00ff",
                    ready="gateway .* between")  # fmt: skip
        for i, part in enumerate(PARTS):
            where = ("--broker", listen) if part == "operator" else ("--can", bus)
            await spawn(part, "-m", "ups.examples.robots", part, *where,
                        "--node-id", hex(0x0D3E_0000 + i))  # fmt: skip
        print(_WATCH.format(bus=bus, broker=listen, catalog=CATALOG, first=first_in_a_shell()),
              flush=True)  # fmt: skip
        if duration is None:
            await asyncio.gather(*(p.wait() for p in children))
        else:
            await asyncio.sleep(duration)
    except asyncio.CancelledError:
        pass  # Ctrl-C or SIGTERM: the way to stop it; the summary follows
    finally:
        for proc in reversed(children):
            with contextlib.suppress(ProcessLookupError):
                proc.terminate()
        for proc in children:
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except TimeoutError:
                proc.kill()
                await proc.wait()
        await asyncio.gather(*pumps, return_exceptions=True)
    wanted = {"BRAKE from TxNode", "BRAKE via the gateway", "speed limit"}
    missing = sorted(w for w in wanted if w not in seen)
    print(
        f"\nIn short: {'everything arrived' if not missing else 'missing: ' + ', '.join(missing)}."
    )
    return 0 if not missing else 1


async def _pump(
    name: str,
    proc: asyncio.subprocess.Process,
    ready: str | None,
    up: asyncio.Future[None],
    seen: set[str],
) -> None:
    """Print a child's output, prefixed; its log only from warnings up. ``up`` is set when a
    stderr line matches ``ready``."""

    async def lines(stream: asyncio.StreamReader | None, log: bool) -> None:
        assert stream is not None
        crashing = False  # within a traceback: every line of it
        async for raw in stream:
            line = raw.decode(errors="replace").rstrip()
            crashing = crashing or line.startswith("Traceback")
            if ready is not None and not up.done() and re.search(ready, line):
                up.set_result(None)
            for mark in ("BRAKE from TxNode", "BRAKE via the gateway", "speed limit"):
                if mark in line:
                    seen.add(mark)
            if not log or crashing or re.search(r" (WARNING|ERROR|CRITICAL): ", line):
                print(f"[{name}] {line}", flush=True)

    await asyncio.gather(lines(proc.stdout, False), lines(proc.stderr, True))
    code = await proc.wait()
    if ready is not None and not up.done():
        up.set_exception(UpsError(f"{name} exited with {code} before it was up"))
    elif code != 0:
        print(f"[{name}] exited with {code}", flush=True)


_WATCH = """
The robot runs as separate processes. Watch it from another shell:{first}
  ups monitor --can {bus} --catalog {catalog}
  ups console --broker {broker} --catalog {catalog}      # then open http://127.0.0.1:8470
  ups ls --broker {broker} --catalog {catalog}
  ups record run.blf --can {bus} --duration 10
Ctrl-C here stops every part.
"""
