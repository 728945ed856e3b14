"""libups under a Hypothesis state machine: random, semi-valid and hostile frames and timer ticks.

The machine plays an honest CAN-ECB (``Model``: it answers Knock, Stage, CLAIM and binding
requests at once, and corrects every forged Bind and Assign at once, as ours does) and every
other node on the bus, and throws at the C node: honest events and transfers on the etags the
CAN-ECB bound, broken transfers (a frame dropped, repeated, swapped, a header bit flipped),
forged Binds, Assigns, Hellos, refusals and verdicts, random frames of any identifier, length
and flags, and time jumps (from just before the 32-bit millisecond clock wraps). Semi-valid
management frames too (issue 41): Binds of every size class naming the node's channels and
etags, refusals, forged answers put right after the node's request (before the CAN-ECB's), and
forged Servings, after which the CAN-ECB stands by (answers and corrects nothing) until it
takes over 4 s after the last one, with a Hello. It checks:

- every event delivered is on a channel the application subscribes to, and the etag it came on
  is bound to that channel's UID (never another channel's event), with the data that was sent;
- every event the node sends is on the etag the CAN-ECB bound to a channel it publishes on;
- every etag the node relies on (``ups_channel_etag``) is the CAN-ECB's for that UID;
- no channel ends failed (``ups_channel_state`` < 0) while the CAN-ECB answers: only a request
  the application made (subscribe, advertise, unsubscribe) that was not bound before the
  CAN-ECB stood by or the controller stalled may end with an error (a refusal, or a Bind of a
  class the node cannot hold, forged while nobody answers stands after 3 s); one the node had
  bound never ends;
- counters never go back.

``test_machine_under_sanitizers`` runs the machine in a child process on ``libups-asan.so``
(AddressSanitizer and UndefinedBehaviorSanitizer, which abort on the first error); the child
needs libasan preloaded into Python, which is why it is a separate process.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

from ups import _canproto as p
from ups import _cantransfer as t
from ups._cnode import ERRORS, FRAME_EXT, FRAME_FD, CNode, Event, build
from ups._errors import ConfigError

from .procs import sanitizer_env

VARIANT = os.environ.get("UPS_CNODE_FUZZ", "full")
NODE_ID = 0x0123_4567_89AB_CDEF
UIDS = [0x1111_0000_0000_0000 + i for i in range(6)]
OTHER = 0x2222_0000_0000_0000  # a channel nobody here uses
SIZES = [0, 8, 64, 1000, 1024, 4096]
ETAGS = [0x10, 0x11, 0x12, 0x13, 0x3000, 0x3001, 0x3400, 0x3401, 0x3800, 0x3FFF, 0x2FFF]
TAKEOVER = 4000  #: ms a CAN-ECB stands by after a Serving of a lower instance (docs/protocol.md)
#: an etag of each size class, anywhere in its range
any_etag = st.one_of(*(st.integers(c.start, c.stop - 1) for c in map(t.class_etags, range(5))))

frames = st.tuples(
    st.integers(0, 0x1FFFFFFF) | st.sampled_from([p.make_id(0, 0x7F, e) for e in range(0x4000)]),
    st.binary(max_size=64),
    st.sampled_from([FRAME_EXT, FRAME_EXT | FRAME_FD, 0, FRAME_EXT | 0x08, FRAME_EXT | 0x10]),
)


class Model:
    """The honest CAN-ECB: TxNode and etag tables, answering the node's frames at once."""

    def __init__(self) -> None:
        self.txnode: int | None = None  # the node's, once assigned
        self.offered: int | None = None
        self.stages: dict[int, set[int]] = {}
        self.etags: dict[int, int] = {}  # uid -> etag
        self.epoch = 0
        self.standby_until: int | None = None  # standing by (a forged Serving) until then
        self.stood_by = False  # ever: a forged Assign may have moved the node meanwhile
        #: the (etag, uid) pairs the node reported (SUB_AT, PUB_AT) since it last stood by
        self.announced: set[tuple[int, int]] = set()

    @property
    def standby(self) -> bool:
        return self.standby_until is not None

    def uid_at(self, etag: int) -> int | None:
        return next((u for u, e in self.etags.items() if e == etag), None)

    def bind(self, uid: int, cls: int) -> int:
        etag = self.etags.get(uid)
        if etag is None or t.size_class(etag) < cls:  # new, or moved to a larger class
            used = set(self.etags.values())
            etag = next(e for e in t.class_etags(cls) if e not in used)
            self.etags[uid] = etag
        return etag

    def corrections(self, msg: p.Management) -> list[p.Management]:
        """What the CAN-ECB sends when it hears a frame it did not send."""
        out: list[p.Management] = []
        if self.standby:
            return out  # it only counts them
        if isinstance(msg, p.Bind):
            if (other := self.uid_at(msg.etag)) is not None and other != msg.uid:
                out.append(p.Bind(msg.etag, other))
            if (etag := self.etags.get(msg.uid)) is not None and etag != msg.etag:
                out.append(p.Bind(etag, msg.uid))
        elif (
            isinstance(msg, p.Assign)
            and msg.node_id == NODE_ID
            and self.txnode is not None
            and msg.txnode != self.txnode
        ):
            out.append(p.Assign(self.txnode, NODE_ID))
        return out

    def answer(self, msg: p.Management) -> list[p.Management]:
        """The CAN-ECB's answer to one frame of the node."""
        if self.standby:
            return []
        if isinstance(msg, p.Knock) and self.txnode is None:
            self.epoch = (self.epoch + 1) % 16
            self.stages[self.epoch] = set()
            return [p.Census(self.epoch)]
        if isinstance(msg, p.Stage) and msg.epoch in self.stages:
            self.stages[msg.epoch].add(msg.stage << 4 | msg.nibble)
            if len(self.stages[msg.epoch]) == 16 and self.txnode is None:
                self.offered = 0x42
                return [p.Offer(0x42, NODE_ID)]
        if isinstance(msg, p.Request) and msg.kind == p.CLAIM:
            if msg.txnode == self.offered and msg.value == NODE_ID:
                self.txnode, self.offered = msg.txnode, None
                return [p.Assign(msg.txnode, NODE_ID)]
            if msg.txnode != self.txnode:
                return [p.Assign(self.txnode, NODE_ID)] if self.txnode is not None else []
        if isinstance(msg, p.Request) and msg.kind in (p.SUB_BIND, p.PUB_BIND):
            if msg.txnode != self.txnode:  # moved by an Assign forged while it stood by
                assert self.stood_by, f"request from TxNode {msg.txnode}"
                return [p.Hello(1)]  # an unknown TxNode asks: nodes claim again
            return [p.Bind(self.bind(msg.value, msg.size_class), msg.value)]
        if isinstance(msg, p.Holds):
            self.announced.add((msg.etag, msg.uid))
            if msg.uid not in self.etags and self.uid_at(msg.etag) is None:
                self.etags[msg.uid] = msg.etag  # a pair in no table: adopted, as ours does
            return self.corrections(p.Bind(msg.etag, msg.uid))
        if isinstance(msg, p.Declare):
            return [p.Grant(msg.etag, msg.txnode, 0x02)]
        return []


class CNodeMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.node = CNode(NODE_ID, variant=VARIANT)
        self.model = Model()
        self.now = 0xFFFF_FF00  # the 32-bit clock wraps within the first steps
        self.channels: dict[int, int] = {}  # channel index -> uid, as the node returned them
        self.subscribed: set[int] = set()  # uids
        self.published: set[int] = set()
        self.tids: dict[tuple[int, int], int] = {}
        self.stalled = False  # the controller's mailboxes are busy: nothing is sent
        self.last_counters = self.node.counters()
        #: forged: a Bind or a refusal of a UID, to go right after the node's next request for it
        self.ambush: p.Bind | p.EtagsFull | p.Failed | p.Limit | None = None
        self.fresh: set[int] = set()  # channels asked by the application, not bound since
        self.excused: set[int] = set()  # ... of which nobody answered for a while

    # --- plumbing --------------------------------------------------------------------------

    def feed(self, can_id: int, data: bytes, flags: int = FRAME_EXT) -> Event | None:
        """Feed one frame; check the event it delivers against the CAN-ECB's table."""
        event = self.node.rx_raw(can_id, data, flags, self.now)
        if event is not None:
            uid = self.channels.get(event.channel)
            assert uid is not None and uid in self.subscribed, f"event on channel {event}"
            etag = can_id & p.ETAG_MASK
            assert self.vouched(uid, etag), f"{event} came on etag {etag:#x}"
        self.drain()
        return event

    def feed_msg(self, msg: p.Management) -> None:
        can_id, data = p.encode(msg)
        assert self.feed(can_id, data) is None

    def drain(self) -> None:
        """Send what the node queued; the CAN-ECB answers each frame at once."""
        for _ in range(0 if self.stalled else 200):
            sent = list(self.node.tx())
            if not sent:
                return
            for can_id, flags, data in sent:
                self.check_sent(can_id, flags, data)

    def check_sent(self, can_id: int, flags: int, data: bytes) -> None:
        assert flags & FRAME_EXT
        if not p.is_management(can_id):
            priority, txnode, etag = p.split_id(can_id)
            assert priority >= 2
            if txnode != self.model.txnode:  # moved by an Assign forged while it stood by: the
                # node follows an Assign at once (docs/protocol.md), and the CAN-ECB puts it
                # back when it serves again (its answer to the node's CLAIM after the Hello)
                assert self.model.stood_by and txnode == self.node.txnode, (
                    f"event from TxNode {txnode:#x}, the node's is {self.model.txnode}"
                )
            uid = self.model.uid_at(etag)
            if uid not in self.published:  # a Bind forged while the CAN-ECB stood by?
                mine = [u for c, u in self.channels.items()
                        if u in self.published and self.node.channel_etag(c) == etag]  # fmt: skip
                assert mine and all(self.vouched(u, etag) for u in mine), (
                    f"event on etag {etag:#x}, bound to {uid}"
                )
            return
        msg = p.decode(can_id, data)  # raises on a malformed frame of the node
        forged = self.ambush
        if (
            isinstance(msg, p.Request)
            and msg.kind in (p.SUB_BIND, p.PUB_BIND)
            and forged is not None
            and msg.value == (forged.value if isinstance(forged, p.Failed) else forged.uid)
        ):
            self.ambush = None
            self.forged_management(forged)  # before the CAN-ECB's answer
        for reply in self.model.answer(msg):
            self.feed_msg(reply)

    def ms(self, dt: int) -> None:
        self.now = (self.now + dt) & 0xFFFFFFFF
        self.node.tick(self.now)
        self.drain()
        until = self.model.standby_until
        if until is not None and (self.now - until) & 0xFFFFFFFF < 1 << 31:
            self.model.standby_until = None  # it takes over: Hello, and it answers again
            self.feed_msg(p.Hello(1))

    def vouched(self, uid: int, etag: int) -> bool:
        """Whether the node may rely on ``etag`` for ``uid``: the CAN-ECB bound it, or a Bind
        forged while it stood by told the node so, and the node has not reported the pair since
        (its answer to the Hello of the takeover does, and the CAN-ECB corrects it or adopts
        it): docs/security.md, a forged Bind misleads the asker until that correction."""
        model = self.model
        return model.etags.get(uid) == etag or (
            model.stood_by and (etag, uid) not in model.announced
        )

    def asked(self, channel: int, waiting: bool, forged: int | None = None) -> None:
        """The application asked for ``channel``: it may fail only if nobody answers.
        ``waiting``: it was waiting already (the request out may go on: what made it fail
        stays); ``forged``: a Bind of that etag answers its request before the CAN-ECB does."""
        if forged is not None:
            self.ambush = p.Bind(forged, self.channels[channel])
        self.fresh.add(channel)
        if not waiting:
            self.excused.discard(channel)
        if self.model.standby or self.stalled:
            self.excused.add(channel)

    def waiting(self, uid: int) -> bool:
        """Whether the node's channel of ``uid`` waits for its etag."""
        channel = next((c for c, u in self.channels.items() if u == uid), None)
        return channel is not None and self.node.channel_state(channel) == 1

    def nobody_answers(self) -> None:
        """The CAN-ECB stands by, or the controller stalls: the requests out may fail."""
        self.excused |= self.fresh

    # --- rules -----------------------------------------------------------------------------

    @initialize()
    def start(self) -> None:
        self.node.start(self.now)
        self.drain()
        for _ in range(5):
            self.ms(1)
        assert self.node.txnode == 0x42

    @rule(dt=st.integers(0, 60) | st.sampled_from([150, 400, 1100, 2500, 6000]))
    def tick(self, dt: int) -> None:
        self.ms(dt)

    @rule(stalled=st.booleans())
    def stall(self, stalled: bool) -> None:
        self.stalled = stalled
        if stalled:
            self.nobody_answers()
        self.drain()

    @rule(i=st.integers(0, len(UIDS) - 1), forged=st.none() | any_etag)
    def subscribe(self, i: int, forged: int | None) -> None:
        """Subscribe; ``forged``: a Bind of that etag answers the request before the CAN-ECB."""
        waiting = self.waiting(UIDS[i])
        try:
            channel = self.node.subscribe(UIDS[i], self.now)
        except ConfigError:  # every channel is in use
            return
        self.channels[channel] = UIDS[i]
        self.subscribed.add(UIDS[i])
        self.asked(channel, waiting, forged)
        self.drain()

    @rule(i=st.integers(0, len(UIDS) - 1), size=st.sampled_from(SIZES), forged=st.none() | any_etag)
    def advertise(self, i: int, size: int, forged: int | None) -> None:
        waiting = self.waiting(UIDS[i])
        try:
            channel = self.node.advertise(UIDS[i], size, self.now)
        except ConfigError:  # every channel is in use, or larger than the node's events
            return
        self.channels[channel] = UIDS[i]
        self.published.add(UIDS[i])
        self.asked(channel, waiting, forged)
        self.drain()

    @rule(i=st.integers(0, len(UIDS) - 1))
    def unsubscribe(self, i: int) -> None:
        uid = UIDS[i]
        channel = next((c for c, u in self.channels.items() if u == uid), None)
        if channel is None or uid not in self.subscribed:
            return
        waiting = self.waiting(uid)
        self.node.unsubscribe(channel)
        self.subscribed.discard(uid)
        if uid not in self.published:
            del self.channels[channel]
        else:
            self.asked(channel, waiting)
        self.drain()

    @rule(i=st.integers(0, len(UIDS) - 1), data=st.binary(max_size=1100))
    def publish(self, i: int, data: bytes) -> None:
        channel = next((c for c, u in self.channels.items() if u == UIDS[i]), None)
        if channel is not None and UIDS[i] in self.published:
            self.node.publish(channel, data)
            self.drain()

    @rule(
        i=st.integers(0, len(UIDS) - 1),
        data=st.binary(max_size=1100),
        sender=st.integers(0, 0x7E),
        fd=st.booleans(),
        mangle=st.sampled_from(["none", "drop", "repeat", "swap", "flip", "cut"]),
        at=st.integers(0, 200),
    )
    def event(self, i: int, data: bytes, sender: int, fd: bool, mangle: str, at: int) -> None:
        """An event of another node on the etag the CAN-ECB bound, maybe broken on the way."""
        etag = self.model.etags.get(UIDS[i])
        if etag is None or sender == self.model.txnode:
            return
        can_id = p.make_id(0x80, sender, etag)
        flags = FRAME_EXT | (FRAME_FD if fd else 0)
        if etag < p.LARGE_FIRST_ETAG:
            parts = [data[:8]]
        else:
            data = data[: t.max_size(etag)]
            tid = self.tids.get((sender, etag), 0)
            self.tids[(sender, etag)] = (tid + 1) & 0x1F
            parts = _mangle(t.segment(data, tid, 64 if fd else 8), mangle, at)
        delivered = []
        for part in parts:
            event = self.feed(can_id, part, flags)
            if event is not None:
                delivered.append(event.data)
        # a broken transfer may still deliver its event (a frame repeated after its end), but
        # only whole and unaltered, and only once
        assert delivered in ([], [parts[0] if etag < p.LARGE_FIRST_ETAG else data])
        if mangle == "none":
            assert len(delivered) == (etag in self.subscribed_etags())

    @rule(etag=st.sampled_from(ETAGS), i=st.integers(0, len(UIDS) - 1))
    def forged_bind(self, etag: int, i: int) -> None:
        msg = p.Bind(etag, UIDS[i])
        self.feed_msg(msg)
        for correction in self.model.corrections(msg):  # the CAN-ECB's, at once
            self.feed_msg(correction)

    @rule(
        msg=st.one_of(
            st.builds(p.Hello, st.integers(0, 2**64 - 1)),
            st.builds(p.Assign, st.integers(0, 0x7E), st.just(NODE_ID)),
            st.builds(p.Offer, st.integers(0, 0x7E), st.just(NODE_ID)),
            st.builds(p.Census, st.integers(0, 15)),
            st.builds(p.Limit, st.integers(0, 0x7E), st.sampled_from(UIDS)),
            st.builds(p.EtagsFull, st.sampled_from(UIDS)),
            st.builds(p.Failed, st.sampled_from([*UIDS, NODE_ID])),
            st.builds(p.TxNodesFull, st.just(NODE_ID)),
            st.builds(p.Grant, st.sampled_from(ETAGS), st.just(0x42), st.integers(0, 255)),
            st.builds(
                p.Refuse,
                st.sampled_from(ETAGS),
                st.just(0x42),
                st.just(0x10),
                st.just(1),
                st.integers(0, 0xFFFF),
            ),
            st.builds(
                p.Holds,
                st.booleans(),
                st.integers(0, 0x7E),
                st.sampled_from(ETAGS),
                st.sampled_from(UIDS),
            ),
        )
    )
    def forged_management(self, msg: p.Management) -> None:
        self.feed_msg(msg)
        for correction in self.model.corrections(msg):
            self.feed_msg(correction)

    @rule(instance=st.integers(0, 2**64 - 1))
    def forged_serving(self, instance: int) -> None:
        """A Serving of a lower instance: the CAN-ECB stands by until TAKEOVER ms after it."""
        self.feed_msg(p.Serving(instance))  # nodes ignore it
        self.model.standby_until = (self.now + TAKEOVER) & 0xFFFFFFFF
        self.model.stood_by = True
        self.model.announced.clear()
        self.nobody_answers()

    @rule(
        k=st.integers(0, 7),
        other=st.integers(0, len(UIDS) - 1),
        etag=any_etag,
        how=st.sampled_from(["its etag, another uid", "its uid, any etag", "ambush"]),
        answer=st.booleans(),
    )
    def semi_valid_bind(self, k: int, other: int, etag: int, how: str, answer: bool) -> None:
        """A Bind aimed at one of the node's channels: its etag to another UID (a
        contradiction: with ``answer``, Bind(etag, its UID) then answers the request it makes
        again, before the CAN-ECB), its UID to an etag of any size class, now or as the answer
        to its next request (before the CAN-ECB's)."""
        if not self.channels:
            return
        channel, uid = sorted(self.channels.items())[k % len(self.channels)]
        own = self.node.channel_etag(channel) or self.model.etags.get(uid, etag)
        if how == "its etag, another uid":
            self.forged_management(p.Bind(own, UIDS[other] if UIDS[other] != uid else OTHER))
            if answer:
                self.ambush = p.Bind(etag, uid)
        elif how == "its uid, any etag":
            self.forged_management(p.Bind(etag, uid))
        else:
            self.ambush = p.Bind(etag, uid)

    @rule(
        msg=st.one_of(
            st.builds(p.EtagsFull, st.sampled_from(UIDS)),
            st.builds(p.Failed, st.sampled_from(UIDS)),
            st.builds(p.Limit, st.just(0x42), st.sampled_from(UIDS)),
        ),
        ambush=st.booleans(),
    )
    def semi_valid_refusal(self, msg: p.EtagsFull | p.Failed | p.Limit, ambush: bool) -> None:
        """A refusal of one of the node's channels (its TxNode's, for Limit), now or as the
        answer to its next request."""
        if ambush:
            self.ambush = msg
        else:
            self.forged_management(msg)

    @rule(frame=frames)
    def random_frame(self, frame: tuple[int, bytes, int]) -> None:
        can_id, data, flags = frame
        if flags & FRAME_EXT and p.is_management(can_id):
            try:
                msg = p.decode(can_id, data)
            except Exception:
                msg = None
            if isinstance(msg, p.Bind | p.Assign):  # a valid forgery: as forged_management
                self.forged_management(msg)
                return
        else:
            _, txnode, _ = p.split_id(can_id)
            if txnode == self.model.txnode:
                return  # that would be the node itself speaking
        event = self.feed(can_id, data, flags)
        if event is not None:  # one frame on a bound etag: it is that channel's, as it is
            assert event.data == data

    @rule(channel=st.integers(0, 40), size=st.integers(0, 9))
    def declare(self, channel: int, size: int) -> None:
        self.node.declare(channel, size, 100, 50, 0, self.now)
        self.drain()

    def subscribed_etags(self) -> set[int]:
        return {self.node.channel_etag(c) for c, u in self.channels.items() if u in self.subscribed}

    # --- invariants ------------------------------------------------------------------------

    @invariant()
    def relies_only_on_the_ecbs_bindings(self) -> None:
        for channel, uid in self.channels.items():
            etag = self.node.channel_etag(channel)
            assert etag == 0 or self.vouched(uid, etag)

    @invariant()
    def no_channel_fails_while_the_ecb_answers(self) -> None:
        for channel in list(self.channels):
            state = self.node.channel_state(channel)
            if state == 2:
                self.fresh.discard(channel)
                self.excused.discard(channel)
            elif state < 0:
                assert channel in self.excused, (
                    f"channel {channel} ({self.channels[channel]:#x}) ended {ERRORS[state]}, "
                    f"though the CAN-ECB answered (the application asked it since: "
                    f"{channel in self.fresh})"
                )

    @invariant()
    def counters_never_go_back(self) -> None:
        counters = self.node.counters()
        assert all(counters[k] >= v for k, v in self.last_counters.items())
        self.last_counters = counters


def _mangle(parts: list[bytes], how: str, at: int) -> list[bytes]:
    if how == "none" or len(parts) < 2:
        return parts
    k = at % len(parts)
    if how == "drop":
        return parts[:k] + parts[k + 1 :]
    if how == "repeat":
        return parts[: k + 1] + parts[k:]
    if how == "swap":
        j = (k + 1) % len(parts)
        parts = list(parts)
        parts[k], parts[j] = parts[j], parts[k]
        return parts
    if how == "flip":  # E, T or a transfer id bit (never S: that would start a transfer)
        bit = (0x40, 0x20, 0x01, 0x10)[at % 4]
        return [*parts[:k], bytes([parts[k][0] ^ bit]) + parts[k][1:], *parts[k + 1 :]]
    return [*parts[:-1], parts[-1][:-1]]  # cut: the last frame one byte short


CNodeMachine.TestCase.settings = settings(
    max_examples=int(
        os.environ.get("UPS_CNODE_FUZZ_EXAMPLES", "600" if VARIANT == "asan" else "200")
    ),
    stateful_step_count=40,
    deadline=None,
    suppress_health_check=list(HealthCheck),
    derandomize=False,
)
TestCNodeMachine = CNodeMachine.TestCase


@pytest.mark.timeout(240 + 30)  # its child's own bound below: a busy machine takes minutes
def test_machine_under_sanitizers() -> None:
    """The same machine in a child process on the library built with ASan and UBSan."""
    if VARIANT == "asan":
        pytest.skip("this is the child")
    lib = build("asan")
    env = {**os.environ, "UPS_CNODE_FUZZ": "asan", **sanitizer_env()}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-s",
            "-x",
            "-p",
            "no:cacheprovider",
            "-p",
            "no:xdist",
            f"{Path(__file__)}::TestCNodeMachine",
        ],  # -s: the sanitizers' reports
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    output = done.stdout[-6000:] + done.stderr[-6000:]
    assert done.returncode == 0, f"{lib} under the machine:\n{output}"
    assert "1 passed" in done.stdout, output
