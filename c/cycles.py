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
  costliest, from random and semi-valid frames (and ticks between them) around the node's
  state, each input from the same state (``Bound``): its cost is its own, and the dearest input
  of each function is recorded and played again by every later run before it searches.

Then the same for libups-ecb, the CAN-ECB in C, on the ecb-small and ecb-full images
(c/cycles_ecb.py: every public ups_ecb_ function through tables filled to their bounds, a
search over frame sequences, and the admission alone over the stream sets dearest to it).

Not covered: flash wait states (at 48 MHz most parts add 1 wait state per flash access unless an
accelerator or cache hides it), interrupts and their latency, and the application's own work.
Writes cycles.json ({"worst": {config: {function: {cycles, instructions}}}, "scenario": the
same for the deterministic workload alone, which tests/test_cnode_m0.py runs again and compares
with a margin; "recorded": {config: {function: {cycles, instructions, steps}}}, the input the
search found dearest for each function, which later runs and tests/test_cnode_m0.py play
again; "ecb", "ecb_scenario", "ecb_recorded": the same per CAN-ECB image, each recorded input
played from the tables filled to their bounds, by later runs and tests/test_cecb_m0.py)
and, with --readme, the tables in README.md between its markers.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from cycles_ecb import ECB, Dearest, Step, admission_worst, ecb_measure, keep  # noqa: E402

from ups import _canproto as p  # noqa: E402
from ups._armnode import RAM, ArmNode, Counts  # noqa: E402
from ups._cantransfer import class_etags, class_for, segment  # noqa: E402

MHZ = 48  #: the clock the table converts cycles at
CONFIGS = ("minimal", "minimal+declare", "full")
NODE_ID = 0x0123_4567_89AB_CDEF
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


class Bound:
    """A node joined and its channels bound (``Drive.join``, ``Drive.channels``): where every
    input of the search starts, and every recorded one when it is played again. An input's
    figures are its own: its steps alone from this state (the RAM as it was, the same clock)."""

    def __init__(self, config: str) -> None:
        self.drive = Drive(config)
        self.drive.join()
        self.used = self.drive.channels()
        mcu = self.drive.node.mcu
        self._ram, self._now = mcu.read(RAM, mcu.ram_size), self.drive.now

    def play(self, steps: list[Step]) -> dict[str, Counts]:
        """Each function's costliest call while ``steps`` run from the bound state."""
        drive, mcu = self.drive, self.drive.node.mcu
        mcu.write(RAM, self._ram)
        drive.now, mcu.worst = self._now, {}
        for step in steps:
            if isinstance(step, int):
                drive.run(step)
            else:
                drive.raw(*step)
        return dict(mcu.worst)


def search(bound: Bound, examples: int, dearest: Dearest) -> None:
    """A Hypothesis search for the frames (and ticks between them) that make ups_rx and
    ups_tick costliest, each input from the bound state: each function's dearest input into
    ``dearest``."""
    from hypothesis import HealthCheck, given, settings, target
    from hypothesis import strategies as st

    etags = [e for _, _, e, _ in bound.used]
    uids = [u for _, u, _, _ in bound.used]
    field = st.one_of(st.sampled_from(etags), st.integers(0, 0x3FFF))
    ident = st.builds(lambda pr, tx, e: (pr << 21) | (tx << 14) | e,
                      st.sampled_from([0, 1, 0x80]),
                      st.sampled_from([ECB, 0x21, bound.drive.txnode]), field)  # fmt: skip
    payload = st.one_of(st.sampled_from([u.to_bytes(8, "big") for u in uids]),
                        st.binary(min_size=0, max_size=8))  # fmt: skip
    frame = st.builds(lambda i, d: (i, d, 1), ident, payload)

    @settings(max_examples=examples, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(st.lists(st.one_of(frame, frame, frame, st.integers(1, 20)), min_size=1, max_size=10))
    def inputs(steps: list[Step]) -> None:
        steps = [*steps, 1]
        worst = bound.play(steps)
        for label in ("ups_rx", "ups_tick"):
            target(float(worst.get(label, Counts()).cycles), label=label)
        keep(dearest, worst, steps)

    inputs()


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
    config: str, recorded: dict[str, list[Step]], runs: tuple[int, ...] = (100, 400)
) -> tuple[dict[str, Counts], dict[str, Counts], Dearest]:
    """(the worst case of each function, the scenario's own figures, each function's dearest
    input). The inputs ``recorded`` by earlier runs (function -> its input) are played first,
    so a worst once found stays in the table unless the code got cheaper for its input (the
    search depends on the constants Hypothesis collects from the project's modules: a change
    anywhere can make it miss what it found before). The search runs with each number of
    examples in ``runs``: Hypothesis explores differently with each, and what one run finds
    another may miss."""
    fixed = scenario(config)
    bound = Bound(config)
    played = {name: bound.play(steps) for name, steps in recorded.items()}
    dearest: Dearest = {n: (w[n], recorded[n]) for n, w in played.items() if n in w}
    for name, worst in played.items():  # a function's own input stays unless another costs more
        keep(dearest, worst, recorded[name])
    for examples in runs:
        search(bound, examples, dearest)
    worst = dict(fixed)
    for name, (counts, _) in dearest.items():
        if counts.cycles > worst.get(name, Counts()).cycles:
            worst[name] = counts
    return worst, fixed, dearest


def steps_json(dearest: Dearest) -> dict[str, dict[str, object]]:
    """Each function's dearest input as cycles.json keeps it: its figures and its steps."""
    return {n: {"cycles": c.cycles, "instructions": c.instructions,
                "steps": [s if isinstance(s, int) else [s[0], s[1].hex(), s[2]] for s in steps]}
            for n, (c, steps) in sorted(dearest.items())}  # fmt: skip


def recorded_steps(data: dict[str, dict[str, list[object]]]) -> dict[str, list[Step]]:
    """A configuration's entry of cycles.json's "recorded": each function's dearest input, as
    Bound.play takes it."""
    return {n: [s if isinstance(s, int) else (int(s[0]), bytes.fromhex(s[1]), int(s[2]))  # type: ignore[index]
                for s in entry["steps"]]
            for n, entry in data.items()}  # fmt: skip


def figures(worst: dict[str, Counts]) -> dict[str, dict[str, int]]:
    return {n: {"cycles": c.cycles, "instructions": c.instructions}
            for n, c in sorted(worst.items())}  # fmt: skip


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


def ecb_table(results: dict[str, dict[str, dict[str, int]]]) -> str:
    """The CAN-ECB's table: a row per function (ups_ecb_rx split), a column per image."""
    names = sorted({n for r in results.values() for n in r},
                   key=lambda n: (n.split(" (")[0], len(n), n))  # fmt: skip
    rows = ["| CAN-ECB: function | " + " | ".join(
        f"{i}: cycles (µs at {MHZ} MHz)" for i in results) + " |",
        "| --- |" + " ---: |" * len(results)]  # fmt: skip
    for name in names:
        cells = []
        for image in results:
            got = results[image].get(name)
            more = "more than " * got.get("stopped", 0) if got else ""
            cells.append("-" if got is None else
                         f"{more}{got['cycles']} ({more}{got['cycles'] / MHZ:.1f})")  # fmt: skip
        rows.append(f"| `{name}` | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main() -> int:
    out = HERE / "cycles.json"
    old = json.loads(out.read_text()) if out.exists() else {}
    before, ecb_before = old.get("recorded", {}), old.get("ecb_recorded", {})
    results, scenarios = {}, {}
    recorded: dict[str, dict[str, dict[str, object]]] = {}
    for config in CONFIGS:
        worst, fixed, dearest = measure(config, recorded_steps(before.get(config, {})))
        results[config], scenarios[config] = figures(worst), figures(fixed)
        recorded[config] = steps_json(dearest)
    ecb: dict[str, dict[str, dict[str, int]]] = {}
    ecb_fixed, ecb_recorded = {}, {}
    for build, image, counts in (("small", "ecb-small", (4,)), ("full", "ecb-full", (4, 16, 32))):
        worst, fixed, dearest = ecb_measure(build, recorded_steps(ecb_before.get(image, {})))
        ecb[image] = {**figures(worst), **admission_worst(image, counts)}
        ecb_fixed[image], ecb_recorded[image] = figures(fixed), steps_json(dearest)
    out.write_text(json.dumps({"worst": results, "scenario": scenarios, "recorded": recorded,
                               "ecb": ecb, "ecb_scenario": ecb_fixed,
                               "ecb_recorded": ecb_recorded}, indent=1) + "\n")  # fmt: skip
    text = table(results) + "\n\n" + ecb_table(ecb)
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
