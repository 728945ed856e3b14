"""The bus of tests/test_cecb_fuzz.py's machine: libups-ecb (``cecb_driver.Ecb``), the honest
nodes (``cecb_nodes.Honest``) and a forger, with every check that a call to the CAN-ECB must
pass (the module docstring of test_cecb_fuzz.py lists them). ``Bus.call`` makes one call and
checks what it left; ``pump`` delivers the frames on the bus until it is quiet: the CAN-ECB's
to the honest nodes (and back to itself, with ``echo``), everyone else's to the CAN-ECB.
"""

from __future__ import annotations

import os
import zlib
from collections import Counter, deque

from ups import _canproto as p
from ups import _cantransfer as t
from ups._errors import DecodeError
from ups.broker._cecb_lib import Config

from .cecb_driver import (
    CANDIDATE,
    FRAME_ERR,
    FRAME_EXT,
    FRAME_FD,
    FRAME_RTR,
    NOTE_STATE,
    STANDBY,
    Ecb,
    tables_of,
)
from .cecb_nodes import Honest, Ledger

TRACE = bool(os.environ.get("UPS_CECB_FUZZ_TRACE"))  #: print every call and its frames
WRAP = 1 << 32
TAKEOVER = 4000  #: ms a standing-by CAN-ECB waits for another's Hello or Serving
SLACK = 5  #: ms a timer may end late (the CAN-ECB compares at its ticks)
ECHOES, ECHO_WINDOW = 16, 1000  #: frames it remembers sending (UPS_ECB_ECHOES), for that long
IDS = [
    0x1234_5678_9ABC_DEF0, 0x1234_5678_9ABC_DEF1, 0x1234_5678_0000_0001, 0x1234_0000_0000_0002,
    0xFEDC_BA98_7654_3210, 0x0000_0000_0000_0007, 0x8000_0000_0000_0000,
]  # fmt: skip
FORGED_IDS = [0xBAD0_0000_0000_0001, 0xBAD0_0000_0000_0002, 0x1234_5678_9ABC_DEF2]
UIDS = [0x5555_0000_0000_0000 + i for i in range(10)]
ECB, FORGER = -1, -2  #: senders besides the honest nodes (their index)


def check16(can_id: int, data: bytes) -> int:
    """The 16-bit check by which libups-ecb knew the frames it sent before 3394f04 (ups_ecb.c,
    check16), to build a forged frame that collides with one it sent."""
    crc = zlib.crc32(data, zlib.crc32(can_id.to_bytes(4, "big") + bytes([len(data)])))
    return ((crc ^ (crc >> 16)) & 0xFFFF) or 1


def is_foreign(can_id: int, flags: int) -> bool:
    return (
        not flags & FRAME_EXT
        or bool(flags & (FRAME_RTR | FRAME_ERR))
        or bool(flags & FRAME_FD and p.is_management(can_id))
    )


class Bus:
    """The C CAN-ECB (started at ``t0`` on its clock), honest nodes and a forger on one bus,
    every call to the CAN-ECB checked (see tests/test_cecb_fuzz.py)."""

    def __init__(self, variant: str, cfg: Config, t0: int, echo: bool) -> None:
        self.variant, self.cfg, self.t0, self.echo = variant, cfg, t0, echo
        self.ecb: Ecb | None = None
        self.honest = [Honest(i) for i in IDS]
        self.queue: deque[tuple[int, int, int, bytes]] = deque()
        self.txl, self.etl = Ledger("TxNode"), Ledger("etag")
        self.flash: bytes | None = None  #: the latest blob the application saved
        self.flash_tables: tuple[dict[int, int], dict[int, int]] = ({}, {})
        #: its tables after the last call (read again when it notes a change of state)
        self.tables: tuple[dict[int, int], dict[int, tuple[int, int]]] = ({}, {})
        self.abs = 0  #: ms since the machine started (the CAN-ECB's clock is t0 + abs mod 2^32)
        self.active: dict[int, int] = {}  #: TxNode -> when a frame of it came last
        self.started = 0  #: when the CAN-ECB last started
        self.foreign_claim = 0  #: when a Hello or Serving of another instance came last
        self.own_hello = 0  #: when the CAN-ECB last said Hello
        self.last: dict[str, int] = {}
        self.roles: set[int] = set()  #: every role it had (the statistics)
        self.stalled = False  #: the controller sends nothing: the CAN-ECB's frames wait
        self.sent = 0  #: frames the CAN-ECB sent
        self.sent_at: deque[int] = deque()  #: the number of each of its frames on the bus
        self.forged_at: dict[int, int] = {}  #: a forged frame (its hash) -> when it came
        self.stolen: Counter[tuple[int, bytes]] = Counter()  #: see deliver
        self.reclaims = 0  #: ``reclaimed`` before the call under way

    def close(self) -> None:
        if self.ecb is not None:
            self.ecb.close()
            self.ecb = None

    @property
    def now(self) -> int:
        return (self.t0 + self.abs) % WRAP

    # --- the CAN-ECB's calls and what every call must leave --------------------------------

    def new_ecb(self, instance: int) -> Ecb:
        if self.ecb is not None:
            self.ecb.close()
        self.ecb = Ecb(self.variant, self.cfg, instance)
        self.last = self.ecb.counters()
        self.tables = self.ecb.nodes(), self.ecb.channels()
        return self.ecb

    def call(
        self, what: str, fn: object, frame: tuple[int, int, bytes] | None = None
    ) -> list[p.Management]:
        """One call (``fn``) on the CAN-ECB and its checks: the blob saved on NOTE_STATE, then
        the frames it queued taken and judged (unless the controller stalls: they wait)."""
        ecb = self.ecb
        assert ecb is not None
        role = ecb.role()
        before = self.last
        tables = self.tables
        self.reclaims = before["reclaimed"]
        waiting = ecb.rosters()
        fn()  # type: ignore[operator]
        self.check_rosters(what, waiting)
        if ecb.notes() & NOTE_STATE:
            self.persist()
            self.tables = ecb.nodes(), ecb.channels()
        # else the tables did not change (the invariant compares them with the blob's)
        counters = ecb.counters()
        for name, value in counters.items():
            assert value >= before[name], f"{what}: counter {name} went back"
        self.last = counters
        self.roles.add(ecb.role())
        moved = {k for k in counters if counters[k] != before[k]}
        if frame is not None:
            self.check_rejected(what, frame, moved, tables)
        if self.reclaimed():
            self.release(self.tables[0], {e: u for e, (u, _) in self.tables[1].items()})
        if self.stalled:
            return []
        sent = ecb.take()
        msgs = [self.check_frame(what, f) for f in sent]
        if TRACE:
            print(f"{self.abs:>8} {what} -> {msgs} role {ecb.role()}")
        assert [f[0] for f in sent] == sorted(f[0] for f in sent), f"{what}: not lowest first"
        if frame is not None and self.rejected(frame):
            assert not msgs, f"{what}: a frame it rejects answered with {msgs}"
        if what != "stall ends":  # else frames of many calls, some older than the tables
            if role == STANDBY and ecb.role() == STANDBY:
                assert all(isinstance(m, p.Probe) for m in msgs), f"{what}: standing by: {msgs}"
            if any(isinstance(m, p.TxNodesFull) for m in msgs):
                assert "nodes_full" in moved, f"{what}: TxNodesFull, nodes_full did not move"
            if any(isinstance(m, p.EtagsFull) for m in msgs):
                assert "channels_full" in moved, f"{what}: EtagsFull, channels_full did not move"
            if any(isinstance(m, p.Limit) for m in msgs):
                assert moved & {"limited", "quota_hit"}, f"{what}: Limit, nothing counted"
            self.check_said(what, msgs)
        self.see(what, msgs)
        for m, (can_id, _, data) in zip(msgs, sent, strict=True):
            if isinstance(m, p.Hello):  # (queued during a stall: when is not known)
                self.own_hello = self.abs
            self.queue.append((ECB, can_id, FRAME_EXT, data))
            self.sent_at.append(self.sent)
            self.sent += 1
        return msgs

    def check_rosters(self, what: str, before: list[int]) -> None:
        """At most UPS_ECB_ROSTERS Rosters wait, one per node entry; one is turned away
        (rosters_full) only when that many of other nodes waited."""
        assert self.ecb is not None
        bound, waiting = self.ecb.config["rosters"], self.ecb.rosters()
        assert len(waiting) <= bound, f"{what}: {len(waiting)} Rosters wait, past {bound}"
        assert len(set(waiting)) == len(waiting), f"{what}: two Rosters of a node: {waiting}"
        if self.ecb.counters()["rosters_full"] > self.last["rosters_full"]:
            assert len(before) == bound, f"{what}: rosters_full with {before} waiting"

    def stall(self, stalled: bool) -> None:
        """The controller stalls (nothing is sent: frames wait in the CAN-ECB's queue, which
        drops what does not fit), or sends again: what waited goes at once."""
        self.stalled = stalled
        if not stalled:
            self.call("stall ends", lambda: None)
            self.pump()

    def check_said(self, what: str, msgs: list[p.Management]) -> None:
        """What an Offer, Uses or Grant says is true of the tables when it is sent."""
        assert self.ecb is not None
        nodes, chans = self.tables
        #: TxNodes given to another in this call (a reclaim): what a Uses queued before it in
        #: the same call says of them was true when queued
        given = {m.txnode for m in msgs if isinstance(m, p.Offer | p.Assign)}
        for m in msgs:
            if isinstance(m, p.Offer):  # a TxNode nobody else holds
                assert nodes.get(m.txnode, m.node_id) == m.node_id, f"{what}: {m}, {nodes}"
            elif isinstance(m, p.Uses) and m.txnode not in given:
                entry = [i for e, (u, i) in chans.items() if u == m.uid]
                assert entry and m.txnode in nodes, f"{what}: {m} of no binding or TxNode"
                _, subscribers, publishers = self.ecb.users(entry[0])
                users = publishers if m.publish else subscribers
                assert users >> m.txnode & 1, f"{what}: {m}, not in its table"
            elif isinstance(m, p.Grant):
                assert 0x02 <= m.priority <= 0x7F, f"{what}: {m}"
                assert m.etag in chans, f"{what}: {m} of an etag not bound"

    def persist(self) -> None:
        """UPS_ECB_NOTE_STATE: the application writes the blob before it sends anything."""
        assert self.ecb is not None
        blob = self.ecb.save()
        assert 0 < len(blob) <= self.ecb.config["blob_max"], f"blob of {len(blob)} bytes"
        assert self.ecb.save(len(blob) - 1) == b"", "a blob written into too small a buffer"
        self.flash = blob
        self.flash_tables = tables_of(self.variant, self.cfg, blob)

    def check_frame(self, what: str, frame: tuple[int, int, bytes]) -> p.Management:
        can_id, flags, data = frame
        assert flags == FRAME_EXT, f"{what}: a frame with flags {flags:#x}"
        assert can_id <= 0x1FFFFFFF and len(data) <= 8
        assert p.is_management(can_id), f"{what}: an event {can_id:#x} from the CAN-ECB"
        assert p.split_id(can_id)[1] == p.MGMT_TXNODE, f"{what}: {can_id:#x} of a node"
        try:
            msg = p.decode(can_id, data)
        except DecodeError as exc:
            raise AssertionError(
                f"{what}: sent a malformed frame {can_id:#x} {data.hex()}"
            ) from exc
        assert isinstance(msg, p.ECB_FRAMES), f"{what}: sent a node's frame {msg}"
        return msg

    @staticmethod
    def rejected(frame: tuple[int, int, bytes]) -> str | None:
        """ "foreign" or "malformed" for a frame the CAN-ECB must reject, else None."""
        can_id, flags, data = frame
        if is_foreign(can_id, flags):
            return "foreign"
        if p.is_management(can_id) and len(data) <= 8:
            try:
                p.decode(can_id, data)
            except DecodeError:
                return "malformed"
        return None

    def check_rejected(
        self, what: str, frame: tuple[int, int, bytes], moved: set[str], tables: object
    ) -> None:
        """A foreign or malformed frame changes nothing and is counted."""
        kind = self.rejected(frame)
        if kind is not None:
            assert kind in moved, f"{what}: a {kind} frame not counted"
            assert self.tables == tables, f"{what}: a {kind} frame changed the tables"

    # --- who holds what -------------------------------------------------------------------

    def reclaimed(self) -> bool:
        return self.last["reclaimed"] > self.reclaims

    def txnode_excuse(self, txnode: int, prior: int, holder: int) -> str | None:
        return None  # a reclaimed TxNode left the ledger when it left the table (see)

    def release(self, nodes: dict[int, int], chans: dict[int, int]) -> None:
        """TxNodes and etags reclaimed past the lease leave the ledger: TxNodes silent that long
        (their honest nodes forget them, and join anew when told to), etags whose entries the
        call reclaimed (their users are contradicted by the next Bind of the etag)."""
        self.etl.drop(lambda etag, uid: chans.get(etag) == uid)
        lease = self.cfg.lease_s * 1000
        for txnode, node_id in list(self.txl.holder.items()):
            silent = self.abs - max(self.active.get(txnode, 0), self.started)
            if nodes.get(txnode) != node_id and silent >= lease - 1000:
                del self.txl.holder[txnode]
                for h in self.honest:
                    if h.txnode == txnode and h.node_id == node_id:
                        h.forget()

    def etag_excuse(self, etag: int, prior: int, holder: int) -> str | None:
        return None  # a reclaimed etag left the ledger when it left the table (see)

    def see(self, what: str, msgs: list[p.Management]) -> None:
        """Assign and Bind sent, then the tables: nothing handed to two holders."""
        assert self.ecb is not None
        nodes, chans = self.tables[0], {e: u for e, (u, _) in self.tables[1].items()}
        assigns = [(m.txnode, m.node_id, f"{what}: {m}") for m in msgs if isinstance(m, p.Assign)]
        binds = [(m.etag, m.uid, f"{what}: {m}") for m in msgs if isinstance(m, p.Bind)]
        for txnode, _, _ in assigns:
            self.active[txnode] = self.abs
        self.txl.see(assigns + [(k, h, f"{what}: table {k:#x}") for k, h in nodes.items()],
                     self.txnode_excuse)  # fmt: skip
        binds += [(k, h, f"{what}: table {k:#x}") for k, h in chans.items()]
        for etag, uid, where in binds:  # never to a smaller class while the table lives
            for had in [e for e, u in self.etl.holder.items() if u == uid and e != etag]:
                assert (
                    t.size_class(etag) >= t.size_class(had)
                    or {(had, uid), (etag, uid)} & self.etl.forged
                    or self.reclaimed()
                ), f"{where}: moved from {had:#x} to a smaller class"
        self.etl.see(binds, self.etag_excuse)
        last: dict[object, p.Management] = {}
        for m in msgs:
            if isinstance(m, p.Assign):
                last[("t", m.txnode)] = last[("n", m.node_id)] = m
            elif isinstance(m, p.Bind):
                last[("e", m.etag)] = last[("u", m.uid)] = m
        if what == "stall ends":  # frames queued by many calls: older than the tables
            return
        for m in {id(m): m for m in last.values()}.values():  # the latest of each in the batch
            if isinstance(m, p.Assign) and m is last[("t", m.txnode)] is last[("n", m.node_id)]:
                assert nodes.get(m.txnode) == m.node_id, f"{what}: sent {m}, not in its table"
                assert self.flash_tables[0].get(m.txnode) == m.node_id, f"{what}: {m} not saved"
            if isinstance(m, p.Bind) and m is last[("e", m.etag)] is last[("u", m.uid)]:
                assert chans.get(m.etag) == m.uid, f"{what}: sent {m}, not in its table"
                assert self.flash_tables[1].get(m.etag) == m.uid, f"{what}: {m} not saved"

    def lost(self) -> None:
        """The table is gone: only what honest nodes still use must be theirs again."""
        held = {(h.txnode, h.node_id) for h in self.honest}
        used = {(ch.etag, uid) for h in self.honest for uid, ch in h.chans.items()}
        self.txl.drop(lambda txnode, node_id: (txnode, node_id) in held)
        self.etl.drop(lambda etag, uid: (etag, uid) in used)
        self.flash, self.flash_tables = None, ({}, {})

    # --- the bus --------------------------------------------------------------------------

    def send(self, sender: int, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        self.queue.append((sender, can_id, FRAME_EXT, data))
        if sender == FORGER:
            self.note_forged(msg)

    def note_forged(self, msg: p.Management) -> None:
        if isinstance(msg, p.Request) and msg.kind == p.CLAIM:
            self.txl.forged.add((msg.txnode, msg.value))
        elif isinstance(msg, p.Holds):
            self.etl.forged.add((msg.etag, msg.uid))

    def pump(self, limit: int = 4000) -> None:
        """Deliver every frame on the bus, and what they make anyone send, until it is quiet."""
        for _ in range(limit):
            if not self.queue:
                return
            sender, can_id, flags, data = self.queue.popleft()
            seq = self.sent_at.popleft() if sender == ECB else 0
            if sender != ECB or self.echo:
                self.deliver(sender, can_id, flags, data, self.sent - seq)
            if sender == ECB:
                msg = p.decode(can_id, data)
                for i, h in enumerate(self.honest):
                    for out in h.hear(msg):
                        self.send(i, out)
        raise AssertionError(f"the bus never went quiet: {list(self.queue)[:8]}")

    def deliver(self, sender: int, can_id: int, flags: int, data: bytes, since: int = 0) -> None:
        """One frame to the CAN-ECB (``since``: for its own, how many it sent since this one)."""
        assert self.ecb is not None
        ecb, now = self.ecb, self.now
        foreign = self.last["foreign_ecb_frames"]
        if not is_foreign(can_id, flags):  # a frame of its TxNode: its lease starts again
            self.active[p.split_id(can_id)[1]] = self.abs
            if p.is_management(can_id) and sender != ECB:
                try:
                    msg = p.decode(can_id, data)
                except DecodeError:
                    msg = None
                if isinstance(msg, p.Hello | p.Serving) and msg.instance != ecb.instance:
                    self.foreign_claim = self.abs
                if sender == FORGER and msg is not None:
                    self.note_forged(msg)
        what = f"rx {can_id:#010x} {flags:#x} {data.hex()}"
        msgs = self.call(what, lambda: ecb.rx(now, can_id, flags, data), (can_id, flags, data))
        if sender != ECB:
            if sender == FORGER:
                self.forged_at[hash((can_id, data))] = self.abs
            self.check_answer(what, can_id, data, msgs)
            return
        # its own frame heard again: nothing to do, nobody else's, unless it sent more than it
        # remembers since (an echo that then takes the place of a later identical frame's
        # steals its recognition), or the forger sent the same frame within the echo window
        # (the CAN-ECB takes the first for its own)
        key = (can_id, data)
        taken = self.last["foreign_ecb_frames"] == foreign
        forged = self.forged_at.get(hash(key), -ECHO_WINDOW)
        if since > ECHOES or self.abs - forged < ECHO_WINDOW:
            self.stolen[key] += taken
        elif not taken and self.stolen[key]:
            self.stolen[key] -= 1
        else:
            assert not msgs, f"{what}: its own frame answered with {msgs}"
            assert taken, f"{what}: its own taken as foreign"

    def check_answer(self, what: str, can_id: int, data: bytes, msgs: list[p.Management]) -> None:
        """A PUB_BIND(c) answered with a Bind gets an etag of class c or larger. A report
        (SUB_AT, PUB_AT) or CLAIM it refuses (past the quota: Limit; no entry left:
        TxNodesFull) is not adopted: after a lost table, that pair is nobody's to it."""
        if not p.is_management(can_id) or p.split_id(can_id)[1] == p.MGMT_TXNODE:
            return
        try:
            msg = p.decode(can_id, data)
        except DecodeError:
            return
        nodes, chans = self.tables
        limited = any(isinstance(m, p.Limit) for m in msgs)
        full = any(isinstance(m, p.TxNodesFull) for m in msgs)
        if isinstance(msg, p.Holds) and limited and chans.get(msg.etag, (0, 0))[0] != msg.uid:
            self.etl.drop(lambda etag, uid: (etag, uid) != (msg.etag, msg.uid))
        claim = isinstance(msg, p.Request) and msg.kind == p.CLAIM
        if claim and full and nodes.get(msg.txnode) != msg.value:
            self.txl.drop(lambda txnode, node_id: (txnode, node_id) != (msg.txnode, msg.value))
        if not isinstance(msg, p.Request) or msg.kind != p.PUB_BIND or not msg.size_class:
            return
        binds = [m for m in msgs if isinstance(m, p.Bind) and m.uid == msg.value]
        if binds:
            assert t.size_class(binds[-1].etag) >= msg.size_class, f"{what}: {msg} got {binds[-1]}"

    def ms(self, dt: int) -> None:
        assert self.ecb is not None
        self.abs += dt
        ecb, now = self.ecb, self.now
        self.call(f"tick +{dt} ms", lambda: ecb.tick(now))
        role = ecb.role()
        candidacy = min(self.cfg.recovery_ms, 2000)
        if role == CANDIDATE and not self.stalled:  # (stalled: its Hello waits, unseen)
            assert self.abs - self.own_hello <= candidacy + SLACK, (
                f"a candidate {self.abs - self.own_hello} ms after its Hello"
            )
        if role == STANDBY:
            assert self.abs - self.foreign_claim <= TAKEOVER + SLACK, (
                f"standing by {self.abs - self.foreign_claim} ms after another's last claim"
            )
        self.pump()

    # --- what the machine's rules do --------------------------------------------------------

    def start(self, instance: int) -> None:
        ecb = self.new_ecb(instance)
        self.call("start", lambda: ecb.start(self.now))
        self.pump()

    def reset(self, instance: int, how: str, at: int, junk: bytes) -> None:
        """The CAN-ECB starts again (a power cycle): from its latest blob (``latest``), none
        (``none``), one with a bit flipped or cut short at ``at``, or ``junk``."""
        self.pump()
        ecb = self.new_ecb(instance)
        blob = self.flash
        if how == "latest" and blob is not None:
            assert ecb.restore(blob) == 0, f"its own blob refused: {blob.hex()}"
            tables = ecb.nodes(), {e: u for e, (u, _) in ecb.channels().items()}
            assert tables == self.flash_tables, "the blob restored other tables"
        elif how in ("flip", "truncate") and blob is not None:
            bad = bytearray(blob)
            if how == "flip":
                bad[at // 8 % len(bad)] ^= 1 << (at % 8)
            else:
                bad = bad[: at % len(bad)]
            assert ecb.restore(bytes(bad)) < 0, f"a blob ({how}) taken: {bytes(bad).hex()}"
            assert ecb.counters()["blob_refused"] == 1, "a refused blob not counted"
            assert ecb.nodes() == {} and ecb.channels() == {}, "a refused blob left tables"
            self.lost()
        elif how == "garbage" and ecb.restore(junk) == 0:  # a valid blob: what it knows now
            self.lost()
            self.flash = junk
            self.flash_tables = ecb.nodes(), {e: u for e, (u, _) in ecb.channels().items()}
        else:
            assert ecb.nodes() == {} and ecb.channels() == {}, "a refused blob left tables"
            self.lost()
        self.last = ecb.counters()
        self.tables = ecb.nodes(), ecb.channels()
        self.started = self.abs
        self.call("start", lambda: ecb.start(self.now))
        self.pump()

    def node_says(self, i: int, frames: list[p.Management]) -> None:
        for f in frames:
            self.send(i, f)
        self.pump()

    def retry(self) -> None:
        for i, h in enumerate(self.honest):
            for f in h.retry():
                self.send(i, f)
        self.pump()

    def settle(self, seconds: int) -> None:
        """Time passes in 25 ms ticks; the nodes repeat their requests every 200 ms."""
        for k in range(seconds * 40):
            self.ms(25)
            if k % 8 == 7:
                self.retry()

    def populate(self, joins: list[int], uses: list[tuple[int, int, int]], period: int = 0) -> None:
        """Honest nodes join and use channels (-1: subscribe, else publish in that class); with
        ``period`` (100 us), each declares a stream on every channel it publishes on."""
        for i in joins:
            self.node_says(i, self.honest[i].join())
        self.settle(3)
        for i, u, cls in uses:
            self.node_says(i, self.honest[i].use(UIDS[u], sub=cls < 0, cls=max(cls, 0)))
        self.settle(1)
        for i, h in enumerate(self.honest):
            for uid in list(h.chans) if period else []:
                self.node_says(i, h.declare(uid, 8, period, period, 0))
        if period:
            self.settle(1)
