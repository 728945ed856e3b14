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
(ups/_armecb.py): every public ups_ecb_ function through tables filled to their bounds
(``ecb_scenario``; ups_ecb_rx split into a DECLARE, which runs the admission, and any other
frame), a Hypothesis search over frame sequences on the full tables, and ups_ecb_rt_admit (and
ups_ecb_rt_response where linked) alone over the stream sets that make them dearest.

Not covered: flash wait states (at 48 MHz most parts add 1 wait state per flash access unless an
accelerator or cache hides it), interrupts and their latency, and the application's own work.
Writes cycles.json ({"worst": {config: {function: {cycles, instructions}}}, "scenario": the
same for the deterministic workload alone, which tests/test_cnode_m0.py runs again and compares
with a margin; "recorded": {config: {function: {cycles, instructions, steps}}}, the input the
search found dearest for each function, which later runs and tests/test_cnode_m0.py play
again; "ecb", "ecb_scenario": the same per CAN-ECB image, "ecb_recorded": the frame
sequences the search found dearest, which tests/test_cecb_m0.py replays after the workload)
and, with --readme, the tables in README.md between its markers.
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from ups import _canproto as p  # noqa: E402
from ups._armnode import RAM, ArmNode, Counts, Mcu, OverBudget, build_image  # noqa: E402
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


Step = int | tuple[int, bytes, int]  #: a step of an input: ms ticked, or a frame (id, data, flags)


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


Dearest = dict[str, tuple[Counts, list[Step]]]  #: function -> its costliest input so far


def _keep(dearest: Dearest, worst: dict[str, Counts], steps: list[Step]) -> None:
    for name, counts in worst.items():
        if counts.cycles > dearest.get(name, (Counts(), []))[0].cycles:
            dearest[name] = (counts, steps)


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
        _keep(dearest, worst, steps)

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
        _keep(dearest, worst, recorded[name])
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


BUDGET = 20_000_000  #: instructions one admission may run in the emulator (it is stopped past
#: them, and the table says "more than"): a search for the worst sets finds calls of hundreds of
#: millions of cycles, which take the emulator many minutes each
STREAM = struct.Struct("<HBBHHBB")  #: ups_ecb_stream_t on Cortex-M (10 bytes, 2-aligned)


class Admission:
    """libups-ecb's admission test (ups_ecb_rt_admit) on the CAN-ECB image of a full bus."""

    def __init__(self, image: str = "ecb-full") -> None:
        elf = build_image(image)
        self.mcu = Mcu(elf, 64 * STREAM.size + 64 * 8 + 64, count=True)
        self.streams = self.mcu.alloc(64 * STREAM.size, 4)
        self.out = self.mcu.alloc(64 * 8, 8)
        self.stopped = False  #: a call was stopped at the budget (since this was last cleared)

    def response(self, streams: list[tuple[int, int, int, int, int, int]]) -> int:
        """The cycles of ups_ecb_rt_response (the full image's analysis for a status display)
        of ``streams`` in their order."""
        blob = b"".join(STREAM.pack(*s, 0) for s in streams)
        self.mcu.write(self.streams, blob)
        self.mcu.call("ups_ecb_rt_response", self.streams, len(streams), 500_000, 0, self.out,
                      budget=BUDGET)  # fmt: skip
        return self.mcu.counts.cycles

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
    image: str = "ecb-full", counts: tuple[int, ...] = (4, 16, 32), examples: int = 15
) -> dict[str, dict[str, int]]:
    """The most cycles ups_ecb_rt_admit took for each number of streams (the sets above, then a
    Hypothesis search maximising them), and whether a call was stopped at the budget; on the
    full image, ups_ecb_rt_response of the same sets too."""
    bench = Admission(image)
    worst: dict[str, dict[str, int]] = {}
    if "ups_ecb_rt_response" in bench.mcu.symbols:
        most = max(bench.response(s) for n in counts for s in admission_sets(n))
        worst[f"ups_ecb_rt_response ({max(counts)} streams)"] = {"cycles": most, "stopped": 0}
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


# --- the CAN-ECB (libups-ecb) -------------------------------------------------------------------

ECB_IMAGES = ("small", "full")  #: ArmEcb's builds: ecb-small and ecb-full
DECLARE_ROW = "ups_ecb_rx (DECLARE: its admission, of up to UPS_ECB_STREAMS streams)"
OTHER_ROW = "ups_ecb_rx (any other frame)"
Frame = tuple[int, bytes, int]  #: (identifier, data, flags) as ups_ecb_rx takes it


def _is_declare(can_id: int) -> bool:
    """A node's DECLARE request: priority 0, a TxNode below 0x7F, the DECLARE etag."""
    return can_id >> 21 == 0 and (can_id >> 14) & 0x7F != ECB and can_id & 0x3FFF == p.DECLARE


class EcbBus:
    """One emulated CAN-ECB (ups/_armecb.py) and the nodes of a bus around it: the frames it
    sends are heard back (its echoes), joiners answer its Census and Queries and claim what it
    offers; each ups_ecb_rx is counted as a DECLARE (its admission) or as any other frame."""

    def __init__(self, build: str) -> None:
        from ups._armecb import ArmEcb

        self.ecb = ArmEcb(build, count=True)
        self.mcu = self.ecb.mcu
        self.size = self.ecb.config
        self.now = 0xFFFF_F000  # the clock wraps during the run
        self.joiners: set[int] = set()
        self.nodes: dict[int, int] = {}  #: node id -> TxNode
        self.pubs: list[tuple[int, int, int]] = []  #: (TxNode, etag, uid) bound to publish
        self.subs: list[tuple[int, int, int]] = []
        self.rows: dict[str, Counts] = {}
        self.declare = DECLARE_ROW

    def _keep(self, name: str) -> None:
        counts = self.mcu.counts
        if counts.cycles > self.rows.get(name, Counts()).cycles:
            self.rows[name] = counts

    def init(self, **cfg: int) -> None:
        from ups.broker.c_ecb import Config

        config = Config.from_buffer_copy(self.ecb.default_config())
        for name, value in cfg.items():
            setattr(config, name, value)
        assert self.ecb.init(bytes(config), 0x5EED_0000_C0DE_0042) == 0

    def start(self) -> None:
        self.ecb.start(self.now)
        self.drain()

    def rx(self, frames: list[Frame], answer: bool = True) -> None:
        """The frames on the bus, lowest identifier first (the same frame of many nodes is one
        frame on the wire), then what the CAN-ECB sends in answer."""
        for can_id, data, flags in sorted(set(frames)):
            self.ecb.rx(self.now, can_id, flags, data)
            self._keep(self.declare if _is_declare(can_id) else OTHER_ROW)
        if answer:
            self.drain()

    def feed(self, *msgs: p.Management) -> None:
        self.rx([(*p.encode(m), 1) for m in msgs])

    def drain(self) -> None:
        """Send the queue (each frame heard back), and the joiners' answers to it."""
        for _ in range(4 * self.size["tx_depth"] + 64):
            self.ecb.notes()
            frame = self.ecb.pop_tx()
            if frame is None:
                return
            can_id, flags, data = frame
            self.ecb.rx(self.now, can_id, flags, data)  # the echo
            self._keep(OTHER_ROW)
            self.rx(self._answers(p.decode(can_id, data)), answer=False)

    def _answers(self, msg: p.Management) -> list[Frame]:
        out: list[p.Management] = []
        if isinstance(msg, p.Census | p.Query):
            start = 0 if isinstance(msg, p.Census) else len(msg.prefix)
            for node_id in self.joiners:
                nib = [(node_id >> (60 - 4 * k)) & 0xF for k in range(16)]
                if isinstance(msg, p.Census) or tuple(nib[:start]) == msg.prefix:
                    out += [p.Stage(msg.epoch, k, nib[k]) for k in range(start, 16)]
        elif isinstance(msg, p.Offer) and msg.node_id in self.joiners:
            out.append(p.Request(p.CLAIM, msg.txnode, msg.node_id))
        elif isinstance(msg, p.Assign) and msg.node_id in self.joiners:
            self.joiners.discard(msg.node_id)
            self.nodes[msg.node_id] = msg.txnode
        elif isinstance(msg, p.Bind):
            for kind in ("pubs", "subs"):
                table = getattr(self, kind)
                table[:] = [(t, msg.etag if u == msg.uid else e, u) for t, e, u in table]
        return [(*p.encode(m), 1) for m in out]

    def run(self, ms: int, step: int = 1) -> None:
        for _ in range(ms // step):
            self.now = (self.now + step) & 0xFFFF_FFFF
            self.ecb.tick(self.now)
            self.drain()

    def ask(self, kind: int, txnode: int, uid: int, size_class: int = 0) -> int | None:
        """A bind request; the etag of the Bind that answers it, or None."""
        self.ecb.rx(self.now, *_swap(p.encode(p.Request(kind, txnode, uid, size_class))))
        self._keep(OTHER_ROW)
        etag = None
        for _ in range(4 * self.size["tx_depth"]):
            frame = self.ecb.pop_tx()
            if frame is None:
                break
            can_id, flags, data = frame
            self.ecb.rx(self.now, can_id, flags, data)
            self._keep(OTHER_ROW)
            msg = p.decode(can_id, data)
            if isinstance(msg, p.Bind) and msg.uid == uid:
                etag = msg.etag
        return etag


def _swap(frame: tuple[int, bytes]) -> tuple[int, int, bytes]:
    return frame[0], 1, frame[1]


def _ids(count: int, seed: int) -> list[int]:
    """Node ids that share long prefixes (the census must query deep to tell them apart)."""
    return [0x0123_4567_89AB_0000 ^ (seed << 40) ^ (k * 0x1111) for k in range(count)]


def ecb_scenario(build: str, recorded: list[list[Frame]] | None = None) -> dict[str, Counts]:
    """Every public ups_ecb_ function driven through tables filled to their bounds on the
    ``build`` image, then the frame sequences the search found dearest (``recorded``) again."""
    return _ecb_finish(_ecb_fill(build), recorded or [])


def _ecb_fill(build: str) -> EcbBus:
    bus = EcbBus(build)
    ecb, size = bus.ecb, bus.size
    nodes, channels, streams = size["nodes"], size["channels"], size["streams"]
    bus.init(recovery_ms=100)
    bus.start()
    census = min(8, nodes // 2)
    for t, node_id in enumerate(_ids(nodes - census, 1)):  # adopted in the recovery window
        bus.feed(p.Request(p.CLAIM, t, node_id))
        bus.nodes[node_id] = t
    bus.run(150)
    bus.joiners.update(_ids(census + 2, 2))  # a census storm: more joiners than TxNodes left
    bus.feed(p.Knock())
    bus.run(600)
    bus.feed(p.Knock())
    bus.run(2000, 10)
    txnodes = sorted(bus.nodes.values())
    # every channel bound, by TxNodes in turn, the larger size classes among them
    for k in range(channels + 4):
        t = txnodes[k % len(txnodes)]
        uid = 0x5000_0000_0000_0000 + k
        if k % 2:
            etag = bus.ask(p.PUB_BIND, t, uid, k % 5)
            if etag is not None:
                bus.pubs.append((t, etag, uid))
        else:
            etag = bus.ask(p.SUB_BIND, t, uid)
            if etag is not None:
                bus.subs.append((t, etag, uid))
        if k % 64 == 63:
            bus.run(20)
    for t, _, uid in bus.pubs[:64]:  # more users of the channels, from other TxNodes
        bus.ask(p.SUB_BIND, txnodes[(txnodes.index(t) + 1) % len(txnodes)], uid)
        bus.ask(p.PUB_BIND, txnodes[(txnodes.index(t) + 2) % len(txnodes)], uid)
    bus.run(200, 10)
    # declarations up to the streams' bound (admission_sets' at 95 % load, each stream declared
    # again by the next set: the admission of the whole table each time; its transfers on the
    # larger classes' etags), then more than the table holds
    small = [(t, e) for t, e, _ in bus.pubs if e < 0x3000]
    large = [(t, e) for t, e, _ in bus.pubs if e >= 0x3000]
    sets = admission_sets(streams + 2)
    for streamset in (sets[5], sets[4], sets[6]):
        for n, (etag, _, size_, period, deadline, jitter) in enumerate(streamset):
            t, e = large[n] if etag >= 0x3000 and n < len(large) else small[n]
            bus.feed(p.Declare(t, e, size_, period, deadline, jitter))
            bus.run(2)  # each TxNode declares a few times: within its burst of DECLAREs
    for n, (etag, _, size_, period, deadline, _) in enumerate(sets[4][:8]):  # overloads: refused
        t, e = large[n] if etag >= 0x3000 and n < len(large) else small[n]
        bus.feed(p.Declare(t, e, size_, period * 8 // 10, deadline * 8 // 10, 0))
        bus.run(2)
    # rosters, contradictions and corrections, another CAN-ECB, foreign and malformed frames
    for t in txnodes[:8]:
        bus.feed(p.Roster(t, 0))
    bus.run(400, 5)  # a frame of the answers every 5 ms
    for t, etag, uid in (bus.pubs + bus.subs)[:32]:
        bus.feed(p.Holds(True, t, etag ^ 1, uid), p.Holds(False, t, etag, uid ^ 0xFF))
        bus.feed(p.Bind(etag, uid ^ 0xFFFF), p.Assign(t, 0x77))
    bus.run(50)
    bus.rx([((0x80 << 21) | (t << 14) | e, bytes(8), 1) for t, e, _ in bus.pubs[:32]])
    bus.rx([((k << 21) | (ECB << 14) | (k * 0x123 & 0x3FFF), bytes(range(k % 9)), 1)
            for k in range(32)])  # fmt: skip
    bus.rx([(0x10 + k, bytes(8), 0) for k in range(8)])  # standard frames
    bus.feed(p.Serving(0xFFFF_FFFF_FFFF_FFFF), p.Probe(9), p.Hello(7))
    bus.run(300, 10)
    for k in range(size["tx_depth"] + 4):  # a full queue, taken frame by frame
        bus.ecb.rx(bus.now, *_swap(p.encode(p.Roster(txnodes[k % len(txnodes)], 0))))
    bus.run(2)
    # the inspection calls over every entry
    ecb.counters()
    ecb.role()
    for i in range(nodes):
        ecb.node(i)
    for i in range(channels):
        ecb.channel(i)
        ecb.channel_use(i, txnodes[i % len(txnodes)])
    # a full blob, saved and taken back; the Hello's answers in the recovery window
    blob = ecb.save()
    bus.init(recovery_ms=2000)
    assert ecb.restore(blob) == 0
    bus.start()
    for node_id, t in list(bus.nodes.items())[::4]:  # every frame costs alike: a quarter answers
        holds = [p.Holds(False, t, e, u) for tt, e, u in bus.subs if tt == t]
        holds += [p.Holds(True, t, e, u) for tt, e, u in bus.pubs if tt == t]
        bus.feed(p.Request(p.CLAIM, t, node_id), *holds)
    bus.run(2100, 10)
    return bus


def _ecb_finish(bus: EcbBus, recorded: list[list[Frame]]) -> dict[str, Counts]:
    """The search's dearest sequences again, then the leases run out (ticks an eighth of a
    lease apart age every entry of the full tables); each function's worst."""
    for batch in recorded:
        bus.rx(batch)
        bus.run(1)
    for _ in range(12):
        bus.now = (bus.now + 86_400_000 // 8) & 0xFFFF_FFFF
        bus.run(1)
    return _rows(bus)


def _rows(bus: EcbBus) -> dict[str, Counts]:
    rows = dict(bus.rows)
    rows.update((n, c) for n, c in bus.mcu.worst.items() if n != "ups_ecb_rx")
    return rows


ECB_EXAMPLES = {"small": 250, "full": 40}  #: the search's examples (some 10 to 20 s each: an
#: example on the full tables costs about 0.5 s in the emulator)


def ecb_measure(
    build: str, seconds: float = 60.0
) -> tuple[dict[str, Counts], dict[str, Counts], list[list[Frame]]]:
    """(the worst case of each function, the scenario's own figures, the search's dearest
    sequences). The search runs on the filled tables of the scenario, whose RAM is then put
    back as it was, so that the scenario goes on as ecb_scenario(build, recorded) runs it; it
    stops at ECB_EXAMPLES[build] examples (the same every run) or, on a machine too busy, after
    ``seconds``."""
    examples = ECB_EXAMPLES[build]
    bus = _ecb_fill(build)
    ram = bus.mcu.read(RAM, bus.mcu.ram_size)
    kept = (bus.now, dict(bus.rows), dict(bus.mcu.worst), dict(bus.nodes), set(bus.joiners),
            list(bus.pubs), list(bus.subs))  # fmt: skip
    found, recorded = _ecb_search(bus, examples, seconds)
    bus.mcu.write(RAM, ram)
    bus.now, bus.rows, bus.mcu.worst, bus.nodes, bus.joiners, bus.pubs, bus.subs = kept
    fixed = _ecb_finish(bus, recorded)
    worst = dict(fixed)
    for name, counts in found.items():
        if counts.cycles > worst.get(name, Counts()).cycles:
            worst[name] = counts
    return worst, fixed, recorded


def _ecb_search(
    bus: EcbBus, examples: int, seconds: float
) -> tuple[dict[str, Counts], list[list[Frame]]]:
    """A Hypothesis search (``target``) for the frame sequences that make ups_ecb_rx and
    ups_ecb_tick costliest on full tables, stopped after ``seconds``: (the worst of each row,
    the sequences that were dearest for ups_ecb_rx, for a DECLARE and for ups_ecb_tick)."""
    import time

    from hypothesis import HealthCheck, given, settings, target
    from hypothesis import strategies as st

    bus.rows, bus.mcu.worst = {}, {}
    txnodes = sorted(bus.nodes.values())
    uses = bus.pubs + bus.subs
    valid = [(*p.encode(m), 1) for m in (
        p.Knock(), *(p.Stage(e, s, n) for e in (0, 1) for s in (0, 15) for n in (0, 0xF)),
        *(p.Request(k, t, u, c) for k in (p.SUB_BIND, p.PUB_BIND, p.UNSUB)
          for t, _, u in uses[:: max(1, len(uses) // 12)] for c in (0, 4)),
        *(p.Request(p.CLAIM, t, i) for i, t in list(bus.nodes.items())[:8]),
        *(p.Declare(t, e, n, 3 * n + 1, 2 * n + 1, n) for t, e, _ in bus.pubs[:12] for n in (1, 8)),
        *(p.Roster(t, c) for t in txnodes[:4] for c in (0, 0x5000_0000_0000_0100)),
        *(p.Holds(pub, t, e ^ x, u) for pub in (False, True) for t, e, u in uses[:6]
          for x in (0, 1)),
        p.Hello(7), p.Serving(3), p.Probe(9), p.Assign(5, 0x77), p.Bind(0x10, 0x7777),
    )]  # fmt: skip
    frames = st.one_of(st.sampled_from(valid), st.sampled_from(valid), st.tuples(
        st.builds(lambda pr, tx, e: (pr << 21) | (tx << 14) | e, st.sampled_from([0, 1, 0x80]),
                  st.sampled_from([ECB, *txnodes[:3]]), st.integers(0, 0x3FFF)),
        st.binary(max_size=8), st.sampled_from([1, 1, 0])))  # fmt: skip
    dearest: dict[str, tuple[int, list[Frame]]] = {}
    stop = time.monotonic() + seconds

    @settings(max_examples=examples, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(st.lists(frames, min_size=1, max_size=8), st.integers(1, 30))
    def search(batch: list[Frame], ms: int) -> None:
        if time.monotonic() > stop:
            return
        most: dict[str, int] = {}
        for can_id, data, flags in batch:
            bus.ecb.rx(bus.now, can_id, flags, data)
            name = bus.declare if _is_declare(can_id) else OTHER_ROW
            bus._keep(name)
            most[name] = max(most.get(name, 0), bus.mcu.counts.cycles)
        bus.drain()
        most["ups_ecb_tick"] = 0
        for _ in range(ms):
            bus.now = (bus.now + 1) & 0xFFFF_FFFF
            bus.ecb.tick(bus.now)
            most["ups_ecb_tick"] = max(most["ups_ecb_tick"], bus.mcu.counts.cycles)
            bus.drain()
        for label, cycles in most.items():
            target(float(cycles), label=label)
            if cycles > dearest.get(label, (0, []))[0]:
                dearest[label] = (cycles, batch)

    search()
    return _rows(bus), [batch for _, batch in dearest.values()]


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


def _frames_json(recorded: list[list[Frame]]) -> list[list[list[object]]]:
    return [[[i, d.hex(), f] for i, d, f in batch] for batch in recorded]


def recorded_frames(data: list[list[list[object]]]) -> list[list[Frame]]:
    """cycles.json's dearest sequences of the search, as ecb_scenario takes them."""
    return [[(int(i), bytes.fromhex(str(d)), int(f)) for i, d, f in batch]  # type: ignore[call-overload]
            for batch in data]  # fmt: skip


def main() -> int:
    out = HERE / "cycles.json"
    before = json.loads(out.read_text()).get("recorded", {}) if out.exists() else {}
    results, scenarios = {}, {}
    recorded: dict[str, dict[str, dict[str, object]]] = {}
    for config in CONFIGS:
        worst, fixed, dearest = measure(config, recorded_steps(before.get(config, {})))
        results[config], scenarios[config] = figures(worst), figures(fixed)
        recorded[config] = steps_json(dearest)
    ecb: dict[str, dict[str, dict[str, int]]] = {}
    ecb_fixed, ecb_recorded = {}, {}
    for build, image, counts in (("small", "ecb-small", (4,)), ("full", "ecb-full", (4, 16, 32))):
        worst, fixed, frames = ecb_measure(build)
        ecb[image] = {**figures(worst), **admission_worst(image, counts)}
        ecb_fixed[image], ecb_recorded[image] = figures(fixed), _frames_json(frames)
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
