#!/usr/bin/env python3
"""Worst-case cycles of libups-ecb, the CAN-ECB in C, on Cortex-M0+ (``make -C c cycles``, whose
c/cycles.py runs this beside the node's part): every public ups_ecb_ function on the ecb-small
and ecb-full images (ups/_armecb.py) through tables filled to their bounds and their leases run
out (``EcbBound``; ups_ecb_rx split into a DECLARE, which runs the admission, and any other
frame), a Hypothesis search over frame sequences, each from the filled tables, whose dearest
input of each function is recorded and played again by every later run before it searches
(``ecb_measure``), and ups_ecb_rt_admit (and ups_ecb_rt_response where linked) alone over the
stream sets that make them dearest (``admission_worst``). The cycles are counted as
c/cycles.py says.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from ups import _canproto as p  # noqa: E402
from ups._armnode import RAM, Counts, Mcu, OverBudget, build_image  # noqa: E402

ECB = 0x7F  #: the CAN-ECB's TxNode
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
        ecb.channel_users(i)
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


def _ecb_finish(bus: EcbBus) -> dict[str, Counts]:
    """The leases run out (ticks an eighth of a lease apart age every entry of the full
    tables); each function's worst."""
    for _ in range(12):
        bus.now = (bus.now + 86_400_000 // 8) & 0xFFFF_FFFF
        bus.run(1)
    return _rows(bus)


def _rows(bus: EcbBus) -> dict[str, Counts]:
    rows = dict(bus.rows)
    rows.update((n, c) for n, c in bus.mcu.worst.items() if n != "ups_ecb_rx")
    return rows


Step = int | Frame  #: a step of an input: ms ticked (the queue sent after each), or a frame
Dearest = dict[str, tuple[Counts, list[Step]]]  #: function -> its costliest input so far


def keep(dearest: Dearest, worst: dict[str, Counts], steps: list[Step]) -> None:
    """Each function of ``worst`` whose call cost more than its dearest input so far: ``steps``
    in its place."""
    for name, counts in worst.items():
        if counts.cycles > dearest.get(name, (Counts(), []))[0].cycles:
            dearest[name] = (counts, steps)


class EcbBound:
    """The tables of the ``build`` image filled to their bounds (``_ecb_fill``): where every
    input of the search starts, and every recorded one when it is played again. An input's
    figures are its own: its steps alone from this state (the RAM as it was, the same clock and
    the same nodes around it)."""

    def __init__(self, build: str) -> None:
        self.bus = bus = _ecb_fill(build)
        self._ram = bus.mcu.read(RAM, bus.mcu.ram_size)
        self._kept = (bus.now, dict(bus.rows), dict(bus.mcu.worst), dict(bus.nodes),
                      set(bus.joiners), list(bus.pubs), list(bus.subs))  # fmt: skip

    def reset(self) -> None:
        """The filled tables again."""
        bus = self.bus
        bus.mcu.write(RAM, self._ram)
        now, rows, worst, nodes, joiners, pubs, subs = self._kept
        bus.now, bus.rows, bus.mcu.worst = now, dict(rows), dict(worst)
        bus.nodes, bus.joiners = dict(nodes), set(joiners)
        bus.pubs, bus.subs = list(pubs), list(subs)

    def play(self, steps: list[Step]) -> dict[str, Counts]:
        """Each function's costliest call while ``steps`` run from the filled tables: frames
        received as they come, a number of ms ticked (the queue sent before and after each)."""
        self.reset()
        bus = self.bus
        bus.rows, bus.mcu.worst = {}, {}
        for step in steps:
            if isinstance(step, int):
                bus.drain()
                bus.run(step)
            else:
                can_id, data, flags = step
                bus.ecb.rx(bus.now, can_id, flags, data)
                bus._keep(bus.declare if _is_declare(can_id) else OTHER_ROW)
        return _rows(bus)

    def finish(self) -> dict[str, Counts]:
        """The workload's own figures: from the filled tables the leases run out."""
        self.reset()
        return _ecb_finish(self.bus)


ECB_EXAMPLES = {"small": 250, "full": 40}  #: the search's examples (some 10 to 20 s each: an
#: example on the full tables costs about 0.5 s in the emulator)


def ecb_measure(
    build: str,
    recorded: dict[str, list[Step]],
    seconds: float = 60.0,
    examples: int | None = None,
) -> tuple[dict[str, Counts], dict[str, Counts], Dearest]:
    """(the worst case of each function, the workload's own figures, each function's dearest
    input). The inputs ``recorded`` by earlier runs (function -> its input) are played first,
    each from the filled tables as the search plays its own, so that a worst once found stays
    in the table unless the code got cheaper for its input (the search stops after
    ``seconds`` on a busy machine, and what it finds depends on the constants Hypothesis
    collects from the project's modules). The search then runs ``examples``
    (ECB_EXAMPLES[build] unless given; 0: none) from the same tables."""
    bound = EcbBound(build)
    played = {name: bound.play(steps) for name, steps in recorded.items()}
    dearest: Dearest = {n: (w[n], recorded[n]) for n, w in played.items() if n in w}
    for name, worst in played.items():  # a function's own input stays unless another costs more
        keep(dearest, worst, recorded[name])
    examples = ECB_EXAMPLES[build] if examples is None else examples
    if examples > 0:
        _ecb_search(bound, examples, seconds, dearest)
    fixed = bound.finish()
    worst = dict(fixed)
    for name, (counts, _) in dearest.items():
        if counts.cycles > worst.get(name, Counts()).cycles:
            worst[name] = counts
    return worst, fixed, dearest


def _ecb_search(bound: EcbBound, examples: int, seconds: float, dearest: Dearest) -> None:
    """A Hypothesis search (``target``) for the frame sequences (and the ms ticked after them)
    that make ups_ecb_rx and ups_ecb_tick costliest on the filled tables, each from those
    tables, stopped after ``seconds``: each function's dearest input into ``dearest``."""
    import time

    from hypothesis import HealthCheck, given, settings, target
    from hypothesis import strategies as st

    bound.reset()  # the frames name the nodes and channels of the filled tables
    bus = bound.bus
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
    stop = time.monotonic() + seconds

    @settings(max_examples=examples, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(st.lists(frames, min_size=1, max_size=8), st.integers(1, 30))
    def search(batch: list[Frame], ms: int) -> None:
        if time.monotonic() > stop:
            return
        steps: list[Step] = [*batch, ms]
        worst = bound.play(steps)
        for label in (DECLARE_ROW, OTHER_ROW, "ups_ecb_tick"):
            target(float(worst.get(label, Counts()).cycles), label=label)
        keep(dearest, worst, steps)

    search()
