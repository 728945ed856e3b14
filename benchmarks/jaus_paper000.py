"""Paper 000's JAUS experiment (its Table 2) on today's machine, beside UPS on CAN.

Paper 000 (a JAUS/EtherCAT bridge, ``../shared/papers/000_*``) times 1000 minimal JAUS
messages -- Set Component Authority: the 16-byte RA 3.3 header and a 1-byte payload, 17 bytes --
each sent by an *Initiator* to a *Receiver* that answers with a message carrying the same
sequence number, one at a time, 100 ms apart. The one-way time is half the round trip; the table
gives its minimum, maximum, mean and standard deviation (Windows XP, Core 2 Quad 2.4 GHz; test
6, a component to its node over UDP on one machine, is the fastest: mean 0.270 ms).

Here ``ups jaus`` is the Receiver, and one run measures, side by side:

1. ``ra33_direct``: the paper's 17 bytes, in RA 3.3's UDP framing (``JAUS01.0`` first), asking
   for an acknowledgement. ``ups jaus`` (a mapping without Set Authority) handles it -- the
   sender holds control, so the component's authority is set -- and answers with an ACK that
   carries the sequence number: component to component, as in the paper's tests 4 and 6.
2. ``judp_direct``: the same in JUDP (AS5669A): transport header, code, 1-byte payload.
3. ``jaus_can_jaus``: JUDP Set Authority, no ACK, to a second ``ups jaus`` whose mapping
   publishes it on a UPS CAN channel; a CAN node in its own process echoes it on a channel
   mapped to Report Authority; the OCU holds an every-change event on Query Authority, and the
   Event carrying the echoed value ends the round trip: JAUS -> UPS CAN node -> JAUS.
4. ``ups_can``: the UPS CAN path in the same run: a CAN node publishes 1 byte and the same echo
   process publishes it back (``get_msg``, awaited ``publish``).
5. ``can_to_jaus``: a UPS CAN event published here until the Event carrying it reaches the OCU
   here. One clock: this one-way time is measured, not halved.
6. Reports per second: a periodic event asked at 10, 100 and 1000 Hz, the rate at which its
   Events arrive; and an every-change event while CAN events stream at 2000/s, its Events per
   second and the changes coalesced (the mapping caps the rate at 1000/s; JAUS's scaled rate
   field cannot confirm more than 1092 Hz).

Unlike the paper, messages are 10 ms apart, not 100 ms (the receiver is idle either way, and a
full run would take minutes a path). A message not answered within a second is counted as lost,
as the paper's zeroed array did. CAN is python-can's udp_multicast, which must stay inside a
private network namespace:

    scripts/netns-run .venv/bin/python -m ups.benchmarks.jaus_paper000 [--messages N]
        [--warmup W] [--gap MS] [--report-seconds S] [--json PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import signal
import statistics
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from ups.benchmarks._jaus_ocu import Ocu, event_value, judp_ack, payload_of, ra33_ack
from ups.benchmarks._procs import Child
from ups.benchmarks.table5 import check_private_namespace, free_udp_port, ups_argv

#: Table 2 of paper 000, one way in ms: (minimum, maximum, mean, standard deviation)
PAPER_TABLE2_MS = {
    1: ("component -> component, two subsystems", (0.417706, 1.643011, 1.333256, 0.053709)),
    2: ("node -> node, two subsystems", (0.417706, 1.099552, 0.837777, 0.038997)),
    3: ("subsystem -> subsystem", (0.275044, 1.045092, 0.308805, 0.028363)),
    4: ("component -> component, same node", (0.417706, 0.656319, 0.510614, 0.031094)),
    5: ("component -> component, two nodes", (0.417706, 1.303495, 1.035215, 0.043867)),
    6: ("component -> its node", (0.227896, 0.392914, 0.270172, 0.021158)),
    7: ("node -> its subsystem", (0.234931, 0.381488, 0.281037, 0.020506)),
    8: ("component -> its subsystem", (0.417706, 0.819728, 0.634676, 0.032273)),
}
PATHS = {
    "ra33_direct": "JAUS RA 3.3, 17 B Set Component Authority -> ups jaus -> ACK",
    "judp_direct": "JAUS JUDP, Set Authority -> ups jaus -> ACK",
    "jaus_can_jaus": "JAUS -> ups jaus -> UPS CAN echo -> ups jaus -> JAUS Event",
    "ups_can": "UPS CAN node -> UPS CAN echo -> back",
    "can_to_jaus": "UPS CAN event -> ups jaus -> JAUS Event (one way, measured)",
}
ECHOES = {"bench/jaus/authority": "bench/jaus/echo", "bench/ups/ping": "bench/ups/pong"}
CATALOG = """\
[channel."bench/jaus/authority"]
fields = [{ name = "authority", type = "u8" }]
[channel."bench/jaus/echo"]
fields = [{ name = "authority", type = "u8" }]
[channel."bench/jaus/unused"]
fields = [{ name = "authority", type = "u8" }]
"""
FACE_MAP = """\
catalog = "catalog.toml"
[message.SetAuthority]
channel = "bench/jaus/authority"
fields.authority = { field = "authority" }
[message.ReportAuthority]
channel = "bench/jaus/echo"
rate = 1000
fields.authority = { field = "authority" }
"""
DIRECT_MAP = """\
catalog = "catalog.toml"
[message.ReportAuthority]
channel = "bench/jaus/unused"
fields.authority = { field = "authority" }
"""
ANSWER_TIMEOUT = 1.0  # seconds: a message unanswered by then is lost
SETUP_TIMEOUT = 60.0


# --- the echo: a UPS CAN node in its own process -----------------------------------------------


async def _echo(cfg: dict[str, Any]) -> None:
    """Publish every event of each ``ECHOES`` channel back on its partner, until stdin closes
    or says anything; then print the node's counters."""
    from ups import Node

    async with Node(can=cfg["bus"], node_id=cfg["node_id"], name="jaus-bench-echo") as node:
        for ping, pong in ECHOES.items():
            await node.advertise(pong)

            def echo(msg: Any, pong: str = pong) -> None:
                node.publish_nowait(pong, msg.data)

            await node.subscribe(ping, callback=echo)
        print(json.dumps({"event": "ready"}), flush=True)
        await asyncio.to_thread(sys.stdin.readline)
        print(json.dumps({"event": "result", "stats": node.stats()}), flush=True)


# --- the run ------------------------------------------------------------------------------------


def summary_ms(one_way_us: list[float]) -> dict[str, float] | None:
    """min, mean, max, std (as Table 2), p50 and p99 of one-way times, in ms."""
    if not one_way_us:
        return None
    ms = sorted(v / 1000 for v in one_way_us)
    return {
        "min": ms[0],
        "mean": statistics.fmean(ms),
        "max": ms[-1],
        "std": statistics.stdev(ms) if len(ms) > 1 else 0.0,
        "p50": statistics.median(ms),
        "p99": ms[min(len(ms) - 1, int(len(ms) * 0.99))],
    }


async def timed(
    one: Callable[[int], Awaitable[float]], count: int, warmup: int, gap: float
) -> dict[str, Any]:
    """``warmup`` + ``count`` calls of ``one(i)`` (a one-way time in µs), ``gap`` seconds
    apart, one at a time; a call that times out is lost."""
    samples: list[float] = []
    lost = 0
    for i in range(warmup + count):
        await asyncio.sleep(gap)  # the paper's pause between messages
        try:
            value = await one(i)
        except TimeoutError:
            lost += 1
            continue
        if i >= warmup:
            samples.append(value)
    return {"n": len(samples), "lost": lost, "one_way_ms": summary_ms(samples)}


class Run:
    def __init__(self, args: argparse.Namespace, tmp: Path) -> None:
        self.args = args
        self.tmp = tmp
        self.bus = f"udp_multicast:239.74.163.3,port={free_udp_port()}"
        self.children: list[Child] = []

    def spawn(self, argv: list[str], label: str) -> Child:
        child = Child(argv, label)
        self.children.append(child)
        return child

    def close(self) -> None:
        for child in reversed(self.children):
            child.stop()

    def start(self) -> tuple[tuple[str, int], tuple[str, int], Child]:
        """The CAN-ECB, the echo and the two components: where each component listens."""
        (self.tmp / "catalog.toml").write_text(CATALOG)
        (self.tmp / "face.jaus.toml").write_text(FACE_MAP)
        (self.tmp / "direct.jaus.toml").write_text(DIRECT_MAP)
        ecb = self.spawn(
            ups_argv("can-broker", "--can", self.bus, "--db", str(self.tmp / "ecb.db")), "ecb"
        )
        ecb.wait_stderr("CAN-ECB on")
        cfg = {"bus": self.bus, "node_id": 0xEC40}
        echo = self.spawn(
            [sys.executable, "-m", "ups.benchmarks.jaus_paper000", "--child", json.dumps(cfg)],
            "echo",
        )
        echo.event(SETUP_TIMEOUT)
        where = []
        for name, jaus_id, node_id in (("direct", "1.1.1", "0xDA1"), ("face", "1.1.2", "0xFACE")):
            component = self.spawn(
                ups_argv("jaus", "--listen", "127.0.0.1:0", "--id", jaus_id, "--map",
                         str(self.tmp / f"{name}.jaus.toml"), "--can", self.bus,
                         "--node-id", node_id),
                f"ups jaus ({name})",
            )  # fmt: skip
            found = component.wait_stderr(r"JAUS component \S+ on ([\d.]+):(\d+)")
            where.append((found.group(1), int(found.group(2))))
        return where[0], where[1], echo

    async def measure(self, direct: tuple[str, int], face: tuple[str, int]) -> dict[str, Any]:
        from ups import Node
        from ups.jaus import SetAuthority

        a = self.args
        count, warmup, gap = a.messages, a.warmup, a.gap / 1000
        paths: dict[str, Any] = {}
        to_direct, to_face = Ocu(direct, (1, 1, 1)), Ocu(face, (1, 1, 2))
        sizes = {}
        try:
            await _take_control(to_direct)

            def acked_trip(
                key: str, send: Callable[..., int], acked: Callable[[bytes, int], bool | None]
            ) -> Callable[[int], Awaitable[float]]:
                """A round trip: Set Authority asking for an ACK, sent by ``send``; the ACK, as
                ``acked`` recognises it."""

                async def one(i: int) -> float:
                    seq = i & 0xFFFF
                    start = time.perf_counter_ns()
                    sizes[key] = send(SetAuthority(i & 0xFF), sequence=seq, ack=True)
                    arrived, _ = await to_direct.receive(lambda d: acked(d, seq), ANSWER_TIMEOUT)
                    return (arrived - start) / 2000

                return one

            ra33 = acked_trip("ra33_direct", to_direct.send_ra33, ra33_ack)
            judp = acked_trip("judp_direct", to_direct.send, judp_ack)

            for key, one in (("ra33_direct", ra33), ("judp_direct", judp)):
                print(f"  {key} ...", file=sys.stderr, flush=True)
                paths[key] = await timed(one, count, warmup, gap)
                paths[key]["message_bytes"] = sizes[key]
                _progress(key, paths[key])
                to_direct.drain()

            async with Node(can=self.bus, node_id=0xBE4C, name="jaus-bench") as node:
                await _take_control(to_face)  # now: control lapses after 5 s of silence
                event_id = await self._every_change(to_face)

                def value_is(value: int) -> Callable[[bytes], int | None]:
                    return lambda d: 1 if event_value(d, event_id) == value else None

                async def face_trip(i: int) -> float:
                    start = time.perf_counter_ns()
                    sizes["jaus_can_jaus"] = to_face.send(SetAuthority(i & 0xFF))
                    arrived, _ = await to_face.receive(value_is(i & 0xFF), ANSWER_TIMEOUT)
                    return (arrived - start) / 2000

                await node.advertise("bench/ups/ping")
                await node.advertise("bench/jaus/echo")
                pong = await node.subscribe("bench/ups/pong", maxlen=64)

                async def ups_trip(i: int) -> float:
                    data = bytes([i & 0xFF])
                    start = time.perf_counter_ns()
                    await node.publish("bench/ups/ping", data)
                    deadline = time.monotonic() + ANSWER_TIMEOUT
                    while (left := deadline - time.monotonic()) > 0:
                        if (await pong.get_msg(timeout=left)).data == data:
                            return (time.perf_counter_ns() - start) / 2000
                    raise TimeoutError

                async def can_to_jaus(i: int) -> float:
                    start = time.perf_counter_ns()
                    await node.publish("bench/jaus/echo", bytes([i & 0xFF]))
                    arrived, _ = await to_face.receive(value_is(i & 0xFF), ANSWER_TIMEOUT)
                    return (arrived - start) / 1000

                for key, one in (("jaus_can_jaus", face_trip), ("ups_can", ups_trip),
                                 ("can_to_jaus", can_to_jaus)):  # fmt: skip
                    print(f"  {key} ...", file=sys.stderr, flush=True)
                    paths[key] = await timed(one, count, warmup, gap)
                    paths[key]["message_bytes"] = sizes.get(key, 1)
                    _progress(key, paths[key])
                    to_face.drain()
                reports = await self._reports(to_face, node, event_id)
                paths["ups_can"]["node_stats"] = node.stats()
        finally:
            to_direct.close()
            to_face.close()
        return {"paths": paths, "reports": reports}

    async def _every_change(self, ocu: Ocu) -> int:
        from ups.jaus import ConfirmEventRequest, CreateEvent, EventType, QueryAuthority
        from ups.jaus import encode_payload as enc

        code, body = enc(QueryAuthority())
        query = code.to_bytes(2, "little") + body
        confirm = await ocu.ask(
            CreateEvent(1, EventType.EVERY_CHANGE, 0.0, query), ConfirmEventRequest
        )
        return int(confirm.event_id)

    async def _reports(self, ocu: Ocu, node: Any, event_id: int) -> dict[str, Any]:
        """Periodic events at 10, 100 and 1000 Hz; the every-change event under a stream."""
        from ups.jaus import (
            CancelEvent,
            ConfirmEventRequest,
            CreateEvent,
            EventType,
            QueryAuthority,
        )
        from ups.jaus import encode_payload as enc

        seconds = self.args.report_seconds
        code, body = enc(QueryAuthority())
        query = code.to_bytes(2, "little") + body
        periodic = []
        for request_id, rate in enumerate((10.0, 100.0, 1000.0), start=2):
            print(f"  periodic {rate:.0f} Hz ...", file=sys.stderr, flush=True)
            confirm = await ocu.ask(
                CreateEvent(request_id, EventType.PERIODIC, rate, query), ConfirmEventRequest
            )
            arrivals = await _arrivals(ocu, confirm.event_id, seconds)
            await ocu.ask(CancelEvent(request_id, confirm.event_id), ConfirmEventRequest)
            ocu.drain()
            periodic.append(
                {"asked_hz": rate, "confirmed_hz": confirm.confirmed_periodic_rate,
                 **_rate_of(arrivals)}
            )  # fmt: skip
        print("  every change under a 2000/s stream ...", file=sys.stderr, flush=True)
        stream_rate, sent = 2000, 0
        collector = asyncio.create_task(_arrivals(ocu, event_id, seconds + 0.5))
        started = time.monotonic()
        while (elapsed := time.monotonic() - started) < seconds:
            due = int(elapsed * stream_rate) + 1
            while sent < due:
                node.publish_nowait("bench/jaus/echo", bytes([sent & 0xFF]))
                sent += 1
            await asyncio.sleep(0.001)
        arrivals = await collector
        change = {"stream_per_s": stream_rate, "changes": sent, **_rate_of(arrivals)}
        change["coalesced_or_lost"] = sent - change["reports"]
        return {"periodic": periodic, "every_change": change}


async def _take_control(ocu: Ocu) -> None:
    from ups.jaus import ConfirmControl, ControlResponse, RequestControl

    got = await ocu.ask(RequestControl(10), ConfirmControl)
    if got.response != ControlResponse.CONTROL_ACCEPTED:
        raise RuntimeError(f"control refused: {got}")


async def _arrivals(ocu: Ocu, event_id: int, seconds: float) -> list[int]:
    """Arrival times (ns) of the Events of ``event_id`` during ``seconds``."""
    from ups.jaus import Event

    out: list[int] = []
    deadline = time.monotonic() + seconds
    with contextlib.suppress(TimeoutError):
        while (left := deadline - time.monotonic()) > 0:
            arrived, _ = await ocu.receive(
                lambda d: 1 if (e := payload_of(d, Event)) and e.event_id == event_id else None,
                left,
            )
            out.append(arrived)
    return out


def _progress(key: str, row: dict[str, Any]) -> None:
    mean = (row["one_way_ms"] or {}).get("mean")
    print(f"    {key}: {row['n']} measured, {row['lost']} lost, mean {_f(mean)} ms",
          file=sys.stderr, flush=True)  # fmt: skip


def _rate_of(arrivals: list[int]) -> dict[str, Any]:
    if len(arrivals) < 2:
        return {"reports": len(arrivals), "measured_hz": None, "interval_ms": None}
    gaps = [(b - a) / 1e6 for a, b in itertools.pairwise(arrivals)]
    return {
        "reports": len(arrivals),
        "measured_hz": (len(arrivals) - 1) / ((arrivals[-1] - arrivals[0]) / 1e9),
        "interval_ms": {"min": min(gaps), "p50": statistics.median(gaps), "max": max(gaps)},
    }


# --- the tables ---------------------------------------------------------------------------------


def _f(value: float | None, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


def tables(doc: dict[str, Any]) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows): one way beside Table 2, then reports per second."""
    test6 = PAPER_TABLE2_MS[6][1][2]
    head = ["path", "bytes", "n", "lost", "min", "mean", "max", "std", "p99", "x paper test 6"]
    body = []
    for test in (6, 4):
        label, (lo, hi, mean, std) = PAPER_TABLE2_MS[test]
        body.append([f"paper 000 test {test}: {label}", "17", "1000", "-", _f(lo), _f(mean),
                     _f(hi), _f(std), "-", _f(mean / test6, ".2f") + "x"])  # fmt: skip
    for key, row in doc["paths"].items():
        s = row["one_way_ms"] or {}
        body.append([PATHS[key], str(row.get("message_bytes", "-")), str(row["n"]),
                     str(row["lost"]), _f(s.get("min")), _f(s.get("mean")), _f(s.get("max")),
                     _f(s.get("std")), _f(s.get("p99")),
                     _f(s["mean"] / test6, ".2f") + "x" if s else "-"])  # fmt: skip
    gap = doc["settings"]["gap_ms"]
    out = [(f"Paper 000's Table 2 beside this machine: one way (ms), half the round trip, "
            f"messages {gap:g} ms apart", head, body)]  # fmt: skip
    r = doc["reports"]
    body = [[f"periodic, asked {p['asked_hz']:g} Hz", _f(p["confirmed_hz"], ".1f"),
             str(p["reports"]), _f(p["measured_hz"], ".1f"),
             _f((p["interval_ms"] or {}).get("p50"), ".2f"),
             _f((p["interval_ms"] or {}).get("max"), ".2f"), "-"]
            for p in r["periodic"]]  # fmt: skip
    c = r["every_change"]
    body.append([f"every change, CAN events at {c['stream_per_s']}/s", "cap 1000",
                 str(c["reports"]), _f(c["measured_hz"], ".1f"),
                 _f((c["interval_ms"] or {}).get("p50"), ".2f"),
                 _f((c["interval_ms"] or {}).get("max"), ".2f"),
                 f"{c['coalesced_or_lost']:,} of {c['changes']:,}"])  # fmt: skip
    head = ["JAUS event", "confirmed Hz", "reports", "reports/s", "interval p50 ms", "max ms",
            "changes coalesced"]  # fmt: skip
    out.append((f"ups jaus: Reports per second, {doc['settings']['report_seconds']:g} s each",
                head, body))  # fmt: skip
    return out


def text(doc: dict[str, Any]) -> str:
    from ups.benchmarks._tables import aligned

    return "\n".join(aligned(tables(doc)))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--messages", type=int, default=1000, help="measured messages a path (1000)")
    p.add_argument("--warmup", type=int, default=100, help="messages before measuring (100)")
    p.add_argument("--gap", type=float, default=10.0, help="ms between messages (10)")
    p.add_argument("--report-seconds", type=float, default=5.0, help="seconds a report rate")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    check_private_namespace()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))  # the children are stopped on the way
    with tempfile.TemporaryDirectory(prefix="ups-jaus-bench-") as tmp:
        run = Run(args, Path(tmp))
        try:
            direct, face, echo = run.start()
            doc = asyncio.run(run.measure(direct, face))
            echo.send("stop")
            doc["echo"] = echo.event(SETUP_TIMEOUT)["stats"]
        finally:
            run.close()
    doc["settings"] = {
        "messages": args.messages,
        "warmup": args.warmup,
        "gap_ms": args.gap,
        "report_seconds": args.report_seconds,
        "bus": run.bus,
        "paper": "000: Table 2, Windows XP SP3, Intel Core 2 Quad 2.4 GHz, 1000 messages "
        "100 ms apart",
    }
    doc["paper_table2_ms"] = {
        str(test): dict(zip(("min", "max", "mean", "std"), figures, strict=True)) | {"label": label}
        for test, (label, figures) in PAPER_TABLE2_MS.items()
    }
    print(text(doc))
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        from ups.benchmarks._table5_roles import run_async

        run_async(_echo(json.loads(sys.argv[2])))
    else:
        sys.exit(main())
