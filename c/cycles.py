#!/usr/bin/env python3
"""Worst-case cycles of libups's public functions on Cortex-M0+ (``make -C c cycles``).

The image ``make size`` links for a board (c/size.py's flags and configurations) runs in an
emulated Cortex-M0+ (ups/_armnode.py: unicorn), which counts each call's instructions and its
cycles by the Cortex-M0+ timing table (ARM DDI 0484C, table 3-1: loads and stores 2, LDM/STM/
PUSH/POP 1+N, POP with PC 3+N, B 2, BL 3, BX/BLX 2, a conditional branch 2 when taken and 1
when not, MULS 1 with the fast multiplier). The workload drives one node through everything a
bus can ask of it, worst first:

- the join: a Knock, a Census whose sixteen answers fill the TX queue, Queries matching its id
  at every length, an Offer and its Assign;
- every channel of the configuration in use (half subscribed, half published; in the full
  configuration the published ones of the largest size class), bound by Binds, a TX queue kept
  full, events of every size received (the largest transfers, frame by frame), a Hello and the
  whole answer to it, contradicting Binds on every channel and the re-binding, refusals and
  verdicts, a full bus of management frames of every row;
- then Hypothesis searches (``target``) for the frames that make ``ups_rx`` and ``ups_tick``
  costliest, from random and semi-valid frames around the node's state.

Not covered: flash wait states (at 48 MHz most parts add 1 wait state per flash access unless an
accelerator or cache hides it), interrupts and their latency, and the application's own work.
Writes cycles.json ({"worst": {config: {function: {cycles, instructions}}}, "scenario": the
same for the deterministic workload alone, which tests/test_cnode_m0.py runs again and compares
with a margin}) and, with --readme, the table in README.md between its markers.
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from ups import _canproto as p  # noqa: E402
from ups._armnode import ArmNode, Counts, Mcu, OverBudget, build_image  # noqa: E402
from ups._cantransfer import class_etags, class_for, segment  # noqa: E402

MHZ = 48  #: the clock the table converts cycles at
CONFIGS = ("minimal", "minimal+declare", "full")
NODE_ID = 0x0123_4567_89AB_CDEF
ECB = 0x7F
LARGEST = 1024  #: the full configuration's UPS_MAX_EVENT: its largest event
MARK_BEGIN, MARK_END = "<!-- cycles:begin -->", "<!-- cycles:end -->"


class Drive:
    """One emulated node and the frames of a bus around it, at a clock that moves on."""

    def __init__(self, config: str) -> None:
        self.fd = config == "full"
        self.node = ArmNode(NODE_ID, fd=self.fd, config=config, count=True)
        self.now = 0xFFFF_F000  # the clock wraps during the run
        self.txnode = 5

    def feed(self, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        self.raw(can_id, data)

    def raw(self, can_id: int, data: bytes, flags: int = 1) -> None:
        self.node.rx_raw(can_id, data, flags, self.now)

    def run(self, ms: int, drain: bool = True) -> None:
        """Tick for ``ms``, sending what the node queues: every millisecond for short runs,
        every 10 ms through the long waits (settling, refusals: a port may tick that seldom
        when ups_idle() allows; it is what keeps the emulated run short)."""
        step = 10 if ms >= 100 else 1
        for _ in range(ms // step):
            self.now = (self.now + step) & 0xFFFF_FFFF
            self.node.tick(self.now)
            if drain:
                list(self.node.tx())

    def join(self) -> None:
        node = self.node
        node.start(self.now)
        self.feed(p.Knock())
        self.feed(p.Census(0))  # sixteen Stage answers: more than the TX queue holds
        self.run(3, drain=False)
        list(node.tx())
        self.run(2)
        nib = [(NODE_ID >> (60 - 4 * k)) & 0xF for k in range(16)]
        for length in range(1, 16):
            self.feed(p.Query(length % 16, tuple(nib[:length])))
            self.run(1)
        self.feed(p.Offer(self.txnode, NODE_ID))
        self.run(2)
        self.feed(p.Assign(self.txnode, NODE_ID))
        self.run(2)
        node.notes()

    def channels(self) -> list[tuple[int, int, int, bool]]:
        """Every channel in use: (index, uid, etag, published), bound."""
        node, used = self.node, []
        count = node.config["channels"]
        large = class_etags(class_for(LARGEST))[0] if self.fd else None
        for k in range(count):
            uid = 0x5000_0000_0000_0000 + k
            publish = k % 2 == 1
            if publish:
                size = LARGEST if large is not None else 8
                index = node.advertise(uid, size, self.now)
                etag = (large + k) if large is not None else 0x10 + k
            else:
                index = node.subscribe(uid, self.now)
                etag = 0x10 + k
            used.append((index, uid, etag, publish))
        self.run(50, drain=False)  # the requests wait for room in a full queue
        for _ in range(40):
            self.run(2)
        for _, uid, etag, _ in used:
            self.feed(p.Bind(etag, uid))
        self.run(1200)  # settle, a publisher's pause before its first event on a larger class
        return used

    def traffic(self, used: list[tuple[int, int, int, bool]]) -> None:
        node = self.node
        mtu = 64 if self.fd else 8
        first = True
        for index, _, etag, publish in used:
            if publish:
                size = LARGEST if etag >= 0x3000 else 8
                if first:  # the largest event, then the queue full and refused
                    for _ in range(node.config["tx_depth"] + 1):
                        node.publish(index, bytes(range(256)) * (size // 256) or bytes(size))
                    first = False
                else:
                    node.publish(index, bytes(8))
                list(node.tx())
                self.run(5)
            else:
                other = 0x21
                event_id = (0x80 << 21) | (other << 14) | etag
                self.raw(event_id, bytes(8))
        if self.fd:  # the largest transfers received, frame by frame
            etag = class_etags(class_for(LARGEST))[0x200]  # free: the published use [k]
            self.feed(p.Bind(etag, used[0][1]))  # the subscribed channel moves up ...
            self.run(20)
            self.feed(p.Bind(etag, used[0][1]))  # ... and the answer to its request again
            self.run(1200)
            for tid in range(2):
                for data in segment(bytes(LARGEST), tid, mtu):
                    self.raw((0x80 << 21) | (0x22 << 14) | etag, data, flags=1 | 2)

    def hello_and_contradictions(self, used: list[tuple[int, int, int, bool]]) -> None:
        for _, uid, _, _ in used:  # each UID bound to the largest class's last etag: a move, or
            self.feed(p.Bind(0x3FFF, uid))  # a refusal where the node cannot take such events
        self.run(20)
        for _, uid, etag, _ in used:
            self.feed(p.Bind(etag, uid))
        self.run(1200)
        self.feed(p.Hello(0x1111))
        self.run(30)
        self.feed(p.Hello(0x2222))  # within a second: answered when it has passed
        self.run(1100)
        for _, uid, etag, _ in used:  # every channel contradicted, then bound again
            self.feed(p.Bind(etag, uid ^ 0xFFFF))
        self.run(20)
        for _, uid, etag, _ in used:
            self.feed(p.Bind(etag, uid))
        self.run(1200)
        for _, uid, _, _ in used:
            self.feed(p.EtagsFull(uid))
            self.feed(p.Limit(self.txnode, uid))
            self.feed(p.Failed(uid))
        self.run(50)
        for _, uid, etag, _ in used:
            self.feed(p.Bind(etag, uid))
        self.run(100)

    def declarations(self, used: list[tuple[int, int, int, bool]]) -> None:
        node = self.node
        for index, _, etag, publish in used:
            if publish:  # a transfer's size is its frames
                node.declare(index, 8 if etag < 0x3000 else 17, 100, 50, 0, self.now)
                self.run(5)
                self.feed(p.Grant(etag, self.txnode, 0x10))
                self.feed(p.Refuse(etag, self.txnode, etag, self.txnode, 0xFFFF))
                self.feed(p.Grant(etag, self.txnode, 0x11))
                self.run(600)

    def management_flood(self) -> None:
        """A bus full of management frames of every row."""
        for k in range(16):
            self.feed(p.Census(k))
            self.feed(p.Query(k, (k % 16,) * (1 + k % 15)))
            self.feed(p.Offer(k, NODE_ID ^ k))
            self.feed(p.Assign(k, NODE_ID ^ (k + 1)))
            self.feed(p.TxNodesFull(NODE_ID ^ k))
            self.feed(p.Serving(k))
            self.feed(p.Probe(k))
            self.raw((ECB << 14) | 0x3F00, b"")  # Knock of another joiner
            self.run(1)
        self.run(1200)

    def finish(self, used: list[tuple[int, int, int, bool]]) -> None:
        node = self.node
        node.filters()
        node.idle()
        node.counters()
        for index, _, _, _ in used:
            node.channel_state(index)
            node.channel_etag(index)
            node.channel_priority(index)
            node.set_priority(index, 0x90)
            node.declaration_state(index)
        for index, _, _, publish in used:
            if not publish:
                node.unsubscribe(index)
        self.run(20)


def search(config: str, examples: int) -> dict[str, Counts]:
    """A Hypothesis search for the frames that make ups_rx and ups_tick costliest."""
    from hypothesis import HealthCheck, given, settings, target
    from hypothesis import strategies as st

    drive = Drive(config)
    drive.join()
    used = drive.channels()
    worst = drive.node.mcu.worst
    etags = [e for _, _, e, _ in used]
    uids = [u for _, u, _, _ in used]

    field = st.one_of(st.sampled_from(etags), st.integers(0, 0x3FFF))
    ident = st.builds(lambda pr, tx, e: (pr << 21) | (tx << 14) | e,
                      st.sampled_from([0, 1, 0x80]), st.sampled_from([ECB, 0x21, drive.txnode]),
                      field)  # fmt: skip
    payload = st.one_of(st.sampled_from([u.to_bytes(8, "big") for u in uids]),
                        st.binary(min_size=0, max_size=8))  # fmt: skip

    @settings(max_examples=examples, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(st.lists(st.tuples(ident, payload), min_size=1, max_size=8))
    def frames(batch: list[tuple[int, bytes]]) -> None:
        most = 0
        for can_id, data in batch:
            drive.raw(can_id, data)
            most = max(most, drive.node.mcu.counts.cycles)
        target(float(most), label="ups_rx")
        drive.run(1)
        target(float(drive.node.mcu.counts.cycles), label="ups_tick")

    frames()
    return worst


def scenario(config: str) -> dict[str, Counts]:
    """The deterministic workload alone (what the test repeats to catch growth)."""
    drive = Drive(config)
    drive.join()
    used = drive.channels()
    drive.traffic(used)
    drive.hello_and_contradictions(used)
    drive.declarations(used)
    drive.management_flood()
    drive.finish(used)
    return dict(drive.node.mcu.worst)


def measure(
    config: str, runs: tuple[int, ...] = (100, 400)
) -> tuple[dict[str, Counts], dict[str, Counts]]:
    """(the worst case of each function, the scenario's own figures). The search runs with
    each number of examples in ``runs``: Hypothesis explores differently with each, and what
    one run finds another may miss."""
    fixed = scenario(config)
    worst = dict(fixed)
    for examples in runs:
        for name, counts in search(config, examples).items():
            if counts.cycles > worst.get(name, Counts()).cycles:
                worst[name] = counts
    return worst, fixed


def figures(worst: dict[str, Counts]) -> dict[str, dict[str, int]]:
    return {n: {"cycles": c.cycles, "instructions": c.instructions}
            for n, c in sorted(worst.items())}  # fmt: skip


BUDGET = 20_000_000  #: instructions one admission may run in the emulator (it is stopped past
#: them, and the table says "more than"): a search for the worst sets finds calls of hundreds of
#: millions of cycles, which take the emulator many minutes each
STREAM = struct.Struct("<HBBHHBB")  #: ups_ecb_stream_t on Cortex-M (10 bytes, 2-aligned)


class Admission:
    """libups-ecb's admission test (ups_ecb_rt_admit) on the CAN-ECB image of a full bus."""

    def __init__(self) -> None:
        elf = build_image("ecb-full")
        self.mcu = Mcu(elf, 64 * STREAM.size + 64, count=True)
        self.streams = self.mcu.alloc(64 * STREAM.size, 4)
        self.out = self.mcu.alloc(8, 4)
        self.stopped = False  #: a call was stopped at the budget (since this was last cleared)

    def admit(self, streams: list[tuple[int, int, int, int, int, int]]) -> tuple[int, int]:
        """(the verdict, its cycles) for (etag, txnode, size, period, deadline, jitter)s; a
        call past BUDGET instructions is stopped: verdict -1, the cycles it took so far."""
        blob = b"".join(STREAM.pack(*s, 0) for s in streams)
        self.mcu.write(self.streams, blob)
        try:
            verdict = self.mcu.call("ups_ecb_rt_admit", self.streams, len(streams), 500_000, 0,
                                    self.out, self.out + 4, budget=BUDGET)  # fmt: skip
        except OverBudget:
            verdict = -1
            self.stopped = True
        return verdict, self.mcu.counts.cycles


def admission_sets(count: int) -> list[list[tuple[int, int, int, int, int, int]]]:
    """Stream sets of ``count`` streams that make Audsley's assignment work hardest: loads near
    the limit (each level tries many candidates before one fits), deadlines shorter than the
    periods, transfers, and a set that fails only at the last level."""
    sets = []
    for load in (70, 85, 95):
        period = max(1, count * 3 * 100 // load)  # 100 us units; a frame is ~0.25 ms at 500k
        sets.append([(0x10 + k, k % 120, 8, period + k, max(1, period * (k + 1) // count), k % 3)
                     for k in range(count)])  # fmt: skip
        sets.append([(0x10 + k, k % 120, 8, period + 3 * k, period, 0) for k in range(count)])
    sets.append([(0x3000 + k if k % 4 == 0 else 0x10 + k, k % 120, 2 if k % 4 == 0 else 8,
                  count * 12 + k, count * 6 + k, 0) for k in range(count)])  # fmt: skip
    return sets


def admission_worst(
    counts: tuple[int, ...] = (4, 16, 32), examples: int = 15
) -> dict[str, dict[str, int]]:
    """The most cycles ups_ecb_rt_admit took for each number of streams (the sets above, then a
    Hypothesis search maximising them), and whether a call was stopped at the budget."""
    bench = Admission()
    worst: dict[str, dict[str, int]] = {}
    for count in counts:
        bench.stopped = False
        fixed = max(bench.admit(streams)[1] for streams in admission_sets(count))
        most = max(fixed, _search(bench, count, examples))
        worst[f"ups_ecb_rt_admit ({count} streams)"] = {"cycles": most,
                                                        "stopped": int(bench.stopped)}  # fmt: skip
    return worst


def _search(bench: Admission, count: int, examples: int) -> int:
    from hypothesis import HealthCheck, given, settings, target
    from hypothesis import strategies as st

    most = 0
    stream = st.tuples(st.integers(0x10, 0x3FFF), st.integers(0, 0x7E), st.integers(1, 8),
                       st.integers(count, count * 40), st.integers(count, count * 40),
                       st.integers(0, 20))  # fmt: skip

    @settings(max_examples=examples, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(st.lists(stream, min_size=count, max_size=count, unique_by=lambda s: (s[0], s[1])))
    def search(streams: list[tuple[int, int, int, int, int, int]]) -> None:
        nonlocal most
        cycles = bench.admit(sorted(streams, key=lambda s: (s[0], s[1])))[1]
        most = max(most, cycles)
        target(float(cycles))

    search()
    return most


def table(results: dict[str, dict[str, dict[str, int]]]) -> str:
    names = sorted({n for r in results.values() for n in r})
    head = "| function | " + " | ".join(f"{c}: cycles (µs at {MHZ} MHz)" for c in results) + " |"
    rows = [head, "| --- |" + " ---: |" * len(results)]
    for name in names:
        cells = []
        for config in results:
            got = results[config].get(name)
            cells.append("-" if got is None else f"{got['cycles']} ({got['cycles'] / MHZ:.1f})")
        rows.append(f"| `{name}` | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def ecb_table(admission: dict[str, dict[str, int]]) -> str:
    rows = [f"| CAN-ECB (ecb-full image) | cycles (ms at {MHZ} MHz) |", "| --- | ---: |"]
    for name, got in admission.items():
        c, more = got["cycles"], "more than " * got["stopped"]
        rows.append(f"| `{name}` | {more}{c} ({more}{c / MHZ / 1000:.1f} ms) |")
    return "\n".join(rows)


def main() -> int:
    results, scenarios = {}, {}
    for config in CONFIGS:
        worst, fixed = measure(config)
        results[config], scenarios[config] = figures(worst), figures(fixed)
    admission = admission_worst()
    out = HERE / "cycles.json"
    out.write_text(json.dumps({"worst": results, "scenario": scenarios,
                               "ecb": admission}, indent=1) + "\n")  # fmt: skip
    text = table(results) + "\n\n" + ecb_table(admission)
    print(text)
    print(f"written: {out}")
    if "--readme" in sys.argv:
        readme = HERE / "README.md"
        body = readme.read_text()
        start, end = body.index(MARK_BEGIN) + len(MARK_BEGIN), body.index(MARK_END)
        readme.write_text(body[:start] + "\n" + text + "\n" + body[end:])
        print(f"written: the table in {readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
