"""libups (c/) rule by rule against docs/protocol.md, frame by frame.

Each test drives one C node (through ``ups._cnode``, ctypes) with frames built by the Python
codec and a clock of its own (``Wire``), or beside the real CAN-ECB where the CAN-ECB's tables
show the effect. Most of them came from a review of the C node against the protocol: each failed
before its fix.
"""

from __future__ import annotations

import ctypes
import re
from pathlib import Path

from ups import _canproto as p
from ups import _cantransfer as t
from ups import name_to_uid
from ups._cnode import ERRORS, FRAME_EXT, FRAME_FD, Event

from .cnode_helpers import CanEcb, Wire, c_nodes, now_ms

A, B = 0xAAAA_0000_0000_0001, 0xAAAA_0000_0000_0002
CMD = name_to_uid("robot/cmd")


# --- joining -------------------------------------------------------------------------------


def test_another_joiners_knock_counts_as_its_own() -> None:
    """Knock retry: a joiner that has neither knocked nor heard a Knock (another joiner's is
    the same frame) for 0.3 s knocks again; one that keeps hearing Knocks does not."""
    w = Wire()
    w.node.start(w.now)
    w.drain()
    for _ in range(8):
        w.tick(250)
        w.feed(p.Knock())  # another joiner's
    assert w.mgmt().count(p.Knock()) == 1
    w.tick(300)
    assert w.mgmt().count(p.Knock()) == 2  # nobody knocked for 0.3 s: it does


def test_claim_answering_an_offer_waits_for_room() -> None:
    """A CLAIM that finds the TX queue full (the answers to a Census fill it) is sent as soon
    as there is room, never dropped."""
    w = Wire(variant="min")  # a TX queue of 4
    w.node.start(w.now)
    w.drain()
    w.feed(p.Census(3))  # 16 Stage frames to send: the queue is full
    w.feed(p.Offer(9, w.node_id))
    for _ in range(10):
        w.drain()
    assert p.Request(p.CLAIM, 9, w.node_id) in w.mgmt()
    assert w.node.counters()["tx_dropped"] == 0


def test_a_refusal_ends_a_join_only_once_it_stood_3_s() -> None:
    """Joining, Refusals: TxNodesFull or Failed of the joiner's id ends the join only once it
    stood 3 s (refusal wait) with no Offer or Assign of its id, counted from the refusal or the
    last Hello, Census or Query after it; meanwhile the joiner does not knock, but answers a
    Census and claims an Offer, which voids the refusal."""
    w = Wire()
    w.node.start(w.now)
    w.drain()
    w.feed(p.TxNodesFull(w.node_id))  # forged: the CAN-ECB's Offer follows
    w.tick(2000)
    assert w.node.join_state == 1
    assert w.mgmt().count(p.Knock()) == 1  # no knock while the refusal is open
    w.feed(p.Offer(9, w.node_id))
    w.drain()
    assert p.Request(p.CLAIM, 9, w.node_id) in w.mgmt()
    w.tick(2000)  # 4 s after the refusal: the Offer voided it
    assert w.node.join_state == 1
    w.feed(p.Assign(9, w.node_id))
    assert w.node.txnode == 9

    w = Wire()
    w.node.start(w.now)
    w.drain()
    w.feed(p.Failed(w.node_id))
    w.tick(2000)
    w.feed(p.Census(2))  # a census under way: its Offer may follow
    w.tick(2990)
    assert w.node.join_state == 1
    w.tick(20)  # 3 s after the Census, with nothing contradicting the refusal: it stands
    assert ERRORS[w.node.join_state] == "FAILED"


def test_a_joiner_takes_no_refusal_that_names_another_node() -> None:
    """TxNodesFull and Failed name the joiner they refuse: one naming another node's id (that
    node's answer, or a forger's) neither stops this joiner knocking nor ends its join (issue
    41: with the id check taken out of ups_join.c, one such frame parked every C joiner, and
    ended its join 3 s later)."""
    w = Wire()
    w.node.start(w.now)
    w.drain()
    other = w.node_id ^ 1
    w.feed(p.TxNodesFull(other))
    w.feed(p.Failed(other))
    w.tick(3500)  # longer than the refusal wait
    assert w.node.join_state == 1
    assert w.mgmt().count(p.Knock()) == 4  # at 0, 0.3, 0.9 and 2.1 s: the knock retry runs
    w.feed(p.Census(1))
    w.drain()
    w.feed(p.Offer(9, w.node_id))
    w.drain()
    assert p.Request(p.CLAIM, 9, w.node_id) in w.mgmt()
    w.feed(p.Assign(9, w.node_id))
    assert w.node.txnode == 9


def test_a_join_reaching_its_give_up_with_a_refusal_open_ends_with_its_error() -> None:
    """A join that reaches its give-up time (30 s) while a refusal is open (Census frames keep
    coming, but no Offer) ends with that refusal's error, not a timeout."""
    w = Wire()
    w.node.start(w.now)
    w.drain()
    w.tick(20_000)
    w.feed(p.TxNodesFull(w.node_id))
    for epoch in range(4):
        w.tick(2000)
        w.feed(p.Census(epoch))
    assert w.node.join_state == 1
    w.tick(2100)  # 30.1 s in all, 2.1 s after the last Census
    assert ERRORS[w.node.join_state] == "TXNODES_FULL"


# --- management frames ----------------------------------------------------------------------


def test_every_row_of_the_table_is_well_formed() -> None:
    """Probe and Serving are CAN-ECB frames a node ignores, not malformed ones; a Grant or a
    DECLARE naming an etag beyond 0x3FFF, or a Grant of a priority outside 0x02-0x7F, is
    malformed."""
    w = Wire()
    w.join()
    for msg in (p.Probe(7), p.Serving(7), p.Hello(7), p.Knock(), p.Census(1)):
        w.feed(msg)
    assert w.node.counters()["malformed"] == 0
    w.feed(p.Grant(0x4000, 5, 2))
    w.feed(p.Declare(3, 0x4010, 1, 10, 10, 0))
    w.feed(p.Grant(0x20, 5, 0x01))
    assert w.node.counters()["malformed"] == 3


def test_the_roster_frames_are_ignored_cleanly() -> None:
    """A gateway's Roster and the CAN-ECB's Uses and RosterEnd need no action from a node: they
    are neither malformed nor answered, in every build; a RosterEnd that says done and names a
    next UID is malformed."""
    for variant in ("full", "min"):
        w = Wire(variant=variant)
        w.join()
        w.drain()
        sent = len(w.mgmt())
        for msg in (p.Roster(5, 0), p.Roster(5, CMD), p.Uses(False, 5, CMD), p.Uses(True, 6, CMD),
                    p.RosterEnd(5, CMD, False), p.RosterEnd(5, 0, True)):  # fmt: skip
            w.feed(msg)
        w.tick(100)
        assert w.node.counters()["malformed"] == 0, variant
        assert len(w.mgmt()) == sent, variant
        can_id, _ = p.encode(p.RosterEnd(5, 0, True))
        w.feed_raw(can_id, CMD.to_bytes(8, "big"))
        assert w.node.counters()["malformed"] == 1, variant


# --- binding --------------------------------------------------------------------------------


def test_sub_at_pub_at_and_unsub_wait_for_room() -> None:
    """SUB_AT, PUB_AT and UNSUB that find the TX queue full are sent once there is room:
    otherwise the CAN-ECB never learns that the node publishes (its DECLARE would be ignored,
    the gateway would not forward its events) or that it left."""
    w = Wire(variant="min")
    w.join()
    a = w.node.subscribe(A, w.now)
    w.bind(a, 0x20, A)
    b = w.node.advertise(B, 8, w.now)
    w.bind(b, 0x21, B)
    for i in range(3):  # events fill the queue but for its last place ...
        assert w.node.publish(b, bytes([i])) == 0
    assert w.node.publish(b, b"no room") == -2
    w.node.subscribe(0xC, w.now)  # ... which a SUB_BIND takes: the queue is full
    assert w.node.advertise(A, 8, w.now) == a  # publishes on A too: PUB_AT(0x20, A)
    w.node.unsubscribe(a)  # ... and no longer subscribes: UNSUB(A)
    mark = len(w.sent)
    w.tick(20)
    assert p.Holds(True, 5, 0x20, A) in w.mgmt(mark)
    assert p.Request(p.UNSUB, 5, A) in w.mgmt(mark)
    assert w.node.counters()["tx_dropped"] == 1  # the event that found no room


def test_no_event_goes_out_on_an_etag_after_its_binding_is_contradicted() -> None:
    """Contradiction rule 1: the node sends no event of the channels involved, including those
    still waiting in its TX queue (the etag may be another channel's by the time they go)."""
    w = Wire(variant="min")
    w.join()
    a = w.node.advertise(A, 8, w.now)
    w.bind(a, 0x20, A)
    assert w.node.publish(a, b"old") == 0  # queued, not sent yet
    w.feed(p.Bind(0x20, B))  # etag 0x20 is B's now
    w.drain()
    assert w.events() == []
    assert w.node.channel_state(a) == 1


def test_no_transfer_frame_goes_out_on_an_etag_after_its_binding_is_contradicted() -> None:
    w = Wire()
    w.join()
    a = w.node.advertise(A, 1000, w.now)
    w.bind(a, 0x3400, A)
    w.tick(200)  # the publisher's pause after a Bind of a larger class
    assert w.node.publish(a, bytes(1000)) == 0  # 144 frames: more than the queue holds
    w.feed(p.Bind(0x3400, B))
    for _ in range(200):
        w.drain()
        w.tick(1)
    assert w.events() == []


async def test_a_role_added_while_the_request_is_out_is_told_to_the_can_ecb(
    bus: str, ecb: CanEcb
) -> None:
    """A channel advertised, then subscribed before the answer to its PUB_BIND: the CAN-ECB
    must learn the subscription too; and, the other way round, a publication that stays when
    the subscription whose SUB_BIND asked for the etag goes."""
    speed_uid = name_to_uid("robot/speed")
    async with c_nodes(bus, 0xC8, 0xC9) as c:
        await c.joined()
        node, other = c.nodes
        await c.bound(other, other.advertise(speed_uid, 8, now_ms()))  # the CAN-ECB knows it
        cmd = node.advertise(CMD, 8, now_ms())  # PUB_BIND queued ...
        assert node.subscribe(CMD, now_ms()) == cmd  # ... and now it subscribes too
        speed = node.subscribe(speed_uid, now_ms())  # SUB_BIND queued ...
        node.advertise(speed_uid, 8, now_ms())
        node.unsubscribe(speed)  # ... and now it only publishes
        await c.bound(node, cmd)
        await c.bound(node, speed)
        txnode = node.txnode
        await c.until(lambda: txnode in ecb.subscribers.get(CMD, ()), timeout=3)
        await c.until(lambda: txnode in ecb.publishers.get(CMD, ()), timeout=3)
        await c.until(lambda: txnode in ecb.publishers.get(speed_uid, ()), timeout=3)
        assert txnode not in ecb.subscribers.get(speed_uid, ())


def test_only_an_answer_to_the_request_of_the_current_roles_counts() -> None:
    """The same, when the PUB_BIND asked before the subscription came is sent (popped) only
    after it: its answer would tell the CAN-ECB nothing of the subscription."""
    w = Wire()
    w.join()
    cmd = w.node.advertise(CMD, 8, w.now)  # PUB_BIND queued
    w.node.subscribe(CMD, w.now)
    mark = len(w.sent)
    w.drain()  # the PUB_BIND goes only now, before any tick
    w.feed(p.Bind(0x20, CMD))  # its answer
    for _ in range(3):
        w.tick(60)
        w.feed(p.Bind(0x20, CMD))
    assert w.node.channel_etag(cmd) == 0x20
    w.tick(5)
    told = w.mgmt(mark)
    assert p.Request(p.SUB_BIND, 5, CMD) in told or p.Holds(False, 5, 0x20, CMD) in told


def test_a_channel_refused_during_the_publishers_pause_stays_refused() -> None:
    """A publisher that advertises larger events asks for their size class (PUB_BIND(c)); one
    refused (EtagsFull, standing its 3 s) during its 150 ms pause after a Bind of class 1-4 is
    refused, not "bound" once the pause is over."""
    w = Wire()
    w.join()
    a = w.node.advertise(A, 100, w.now)
    w.bind(a, 0x3400, A)  # class 2: the pause begins
    w.node.advertise(A, 2000, w.now)  # class 3
    w.tick(1)
    assert w.mgmt()[-1] == p.Request(p.PUB_BIND, 5, A, 3)
    w.feed(p.EtagsFull(A))
    w.tick(200)
    assert w.node.channel_state(a) == 1  # waiting: the refusal has not stood yet
    w.tick(2900)
    assert ERRORS[w.node.channel_state(a)] == "ETAGS_FULL"


def test_a_refusal_ends_a_binding_request_only_once_it_stood_3_s() -> None:
    """Binding: EtagsFull, Failed and Limit are refusals; the node keeps repeating its request
    (request retry) and the refusal ends the request only once it stood 3 s with no Bind
    answering the request; a Bind that answers it voids the refusal."""
    w = Wire()
    w.join()
    a = w.node.subscribe(A, w.now)
    b = w.node.subscribe(B, w.now)
    w.tick(1)
    w.feed(p.EtagsFull(A))
    w.feed(p.Limit(5, B))
    mark = len(w.sent)
    w.tick(1000)
    assert w.mgmt(mark).count(p.Request(p.SUB_BIND, 5, A)) >= 3  # still asking
    w.feed(p.Bind(0x21, B))  # the CAN-ECB's answer: the refusal of B was forged
    w.tick(1990)
    assert w.node.channel_state(a) == 1
    assert w.node.channel_etag(b) == 0x21
    w.tick(20)  # 3 s after the refusal, no Bind for A: it stands
    assert ERRORS[w.node.channel_state(a)] == "ETAGS_FULL"
    assert w.node.channel_etag(b) == 0x21


def test_a_refusal_heard_before_the_request_went_is_no_answer_to_it() -> None:
    """A refusal, like a Bind, answers a request only once the request was sent: one heard
    before (anyone's, or a forger's) does not end it 3 s later (found by the state machine,
    issue 41)."""
    w = Wire()
    w.join()
    a = w.node.subscribe(A, w.now)  # its SUB_BIND goes at the next tick
    w.feed(p.EtagsFull(A))
    w.tick(3100)
    assert w.node.channel_state(a) == 1
    w.feed(p.Bind(0x20, A))
    assert w.node.channel_etag(a) == 0x20


def test_a_late_tick_repeats_the_request_before_a_refusal_stands() -> None:
    """A refusal stands once it stood 3 s while the node kept asking: a tick that comes 4 s
    late sends the repeat that fell due meanwhile, and the answer to it voids the refusal
    (found by the state machine, issue 41: the refusal stood at that tick, before the repeat
    went)."""
    w = Wire()
    w.join()
    a = w.node.subscribe(A, w.now)
    w.tick(1)
    w.feed(p.EtagsFull(A))  # forged
    w.now += 4000  # the next tick comes 4 s late
    w.node.tick(w.now)
    assert p.Request(p.SUB_BIND, 5, A) in [p.decode(i, d) for i, _, d in w.drain()]
    assert w.node.channel_state(a) == 1
    w.feed(p.Bind(0x20, A))  # the CAN-ECB's answer to it
    assert w.node.channel_etag(a) == 0x20


def test_a_request_reaching_its_timeout_with_a_refusal_open_ends_with_its_error() -> None:
    """A request that reaches its 5 s timeout with a refusal open ends with that refusal's
    error, not a timeout."""
    w = Wire()
    w.join()
    a = w.node.advertise(A, 8, w.now)
    w.tick(4000)
    w.feed(p.Failed(A))
    w.tick(1400)
    assert w.node.channel_state(a) == 1
    w.tick(300)  # past the 5 s (the ninth wait of the request retry ends at 5.55 s)
    assert ERRORS[w.node.channel_state(a)] == "FAILED"


def test_a_forged_answer_to_a_re_binding_corrected_at_once_is_never_relied_on() -> None:
    """Settling: a node re-binding after a contradiction relies on an answer only once it stood
    50 ms with no Bind contradicting it. A forged answer that the CAN-ECB's true Bind follows at
    once is spoilt: the node asks again and relies on the CAN-ECB's etag, never on the forged
    one (issue 41: with UPS__CAND taken out of the contradiction test of ups__on_bind, the
    forged etag was relied on 50 ms later and the true Bind ignored)."""
    w = Wire()
    w.join()
    a = w.node.subscribe(A, w.now)
    w.bind(a, 0x20, A)
    w.feed(p.Bind(0x20, B))  # a contradiction: the node asks again
    w.tick(1)
    assert w.mgmt()[-1] == p.Request(p.SUB_BIND, 5, A)
    mark = len(w.sent)
    w.feed(p.Bind(0x30, A))  # forged, the moment the request went
    w.feed(p.Bind(0x20, A))  # the CAN-ECB's answer, right after it
    etags = set()
    for _ in range(200):
        w.tick(1)
        etags.add(w.node.channel_etag(a))
        if p.Request(p.SUB_BIND, 5, A) in w.mgmt(mark):  # asked again: answered again
            w.feed(p.Bind(0x20, A))
            mark = len(w.sent)
    assert etags == {0, 0x20}  # waiting, then the CAN-ECB's etag: never the forged one
    assert w.feed_raw(p.make_id(0x80, 9, 0x30), b"\x01") is None
    assert w.feed_raw(p.make_id(0x80, 9, 0x20), b"\x02") == Event(a, b"\x02", 0x80, 9)


def test_a_bind_of_a_size_class_the_node_cannot_hold_is_taken_as_a_refusal() -> None:
    """A Bind answering a subscription with an etag whose events would not fit the node (class
    1 in the minimal build) is a refusal (issue 41): the node keeps asking, the CAN-ECB's own
    answer wins, and it ends the request (UPS_ERR_TOO_LARGE, UNSUB) only once it stood 3 s
    with no Bind that fits answering the request. Before, it ended it at once."""
    w = Wire(variant="min")
    w.join()
    a = w.node.subscribe(A, w.now)
    w.tick(1)
    w.feed(p.Bind(0x3000, A))  # forged: the CAN-ECB's answer follows
    mark = len(w.sent)
    w.tick(500)
    assert w.node.channel_state(a) == 1
    assert w.mgmt(mark).count(p.Request(p.SUB_BIND, 5, A)) >= 2  # still asking
    w.feed(p.Bind(0x20, A))
    assert w.node.channel_etag(a) == 0x20
    w.tick(3000)
    assert w.node.channel_etag(a) == 0x20
    assert p.Request(p.UNSUB, 5, A) not in w.mgmt()

    w = Wire(variant="min")
    w.join()
    a = w.node.subscribe(A, w.now)
    w.tick(1)
    w.feed(p.Bind(0x3000, A))  # the CAN-ECB's: the channel carries up to 64 bytes
    mark = len(w.sent)
    w.tick(2990)
    assert w.node.channel_state(a) == 1
    w.feed(p.Bind(0x3000, A))  # its answer to a repeated request: the same
    w.tick(20)  # 3 s after the first, nothing that fits: it stands
    assert ERRORS[w.node.channel_state(a)] == "TOO_LARGE"
    assert p.Request(p.UNSUB, 5, A) in w.mgmt(mark)
    assert w.node.filters() == [(0x7F << 14, 0x7F << 14)]


def test_a_channel_being_bound_again_keeps_asking_whatever_class_a_bind_names() -> None:
    """Forged frames cannot end a subscription (issue 41): once its binding is contradicted the
    channel keeps asking, as it does through refusals; a Bind of a size class it cannot hold
    does not end it either, and the CAN-ECB's answer, when it comes, binds it again."""
    w = Wire(variant="min")
    w.join()
    a = w.node.subscribe(A, w.now)
    w.bind(a, 0x20, A)
    w.feed(p.Bind(0x20, B))  # forged: the node asks again
    w.tick(1)
    assert w.mgmt()[-1] == p.Request(p.SUB_BIND, 5, A)
    w.feed(p.Bind(0x3000, A))  # forged, of a class it cannot hold
    w.feed(p.EtagsFull(A))
    for _ in range(3):
        w.tick(4000)  # the CAN-ECB stands by: nobody answers
        assert w.node.channel_state(a) == 1
    w.feed(p.Bind(0x20, A))  # it serves again: its answer to the request repeated meanwhile
    w.tick(60)  # settled
    assert w.node.channel_etag(a) == 0x20
    assert p.Request(p.UNSUB, 5, A) not in w.mgmt()
    assert w.feed_raw(p.make_id(0x80, 9, 0x20), b"\x01") == Event(a, b"\x01", 0x80, 9)


def test_a_channel_that_publishes_and_cannot_receive_its_class_stays_a_publisher() -> None:
    """A channel the node both publishes on and subscribes to, answered with an etag of a class
    it cannot receive: once that stood 3 s the node gives up only the subscription (UNSUB), and
    asks again as a publisher."""
    w = Wire()  # events up to 4096 bytes: class 4 does not fit
    w.join()
    a = w.node.subscribe(A, w.now)
    assert w.node.advertise(A, 8, w.now) == a
    w.tick(1)
    w.feed(p.Bind(0x3C00, A))
    mark = len(w.sent)
    w.tick(3010)
    assert p.Request(p.UNSUB, 5, A) in w.mgmt(mark)
    assert p.Request(p.PUB_BIND, 5, A) in w.mgmt(mark)
    assert w.node.channel_state(a) == 1
    w.feed(p.Bind(0x3C00, A))
    assert w.node.channel_etag(a) == 0x3C00
    assert w.node.filters() == [(0x7F << 14, 0x7F << 14)]  # it receives nothing


def test_events_never_crowd_the_frames_owed_to_the_can_ecb_out() -> None:
    """A node that publishes as fast as its queue drains still answers Hello (and sends its
    requests): events leave the queue's last place to management frames."""
    w = Wire(variant="min")
    w.join()
    a = w.node.advertise(A, 8, w.now)
    w.bind(a, 0x20, A)
    w.feed(p.Hello(1))
    mark = len(w.sent)
    for _ in range(50):
        while w.node.publish(a, b"x") == 0:
            pass
        w.tick(1, drain=False)
        sending = w.node.tx()
        w.sent.append(next(sending))  # the controller takes one frame a millisecond
    assert p.Request(p.CLAIM, 5, w.node_id) in w.mgmt(mark)
    assert p.Holds(True, 5, 0x20, A) in w.mgmt(mark)


# --- the answer to Hello --------------------------------------------------------------------


def test_the_answer_to_hello_keeps_its_order_when_the_queue_is_slow() -> None:
    """CLAIM, then SUB_AT/PUB_AT, then DECLARE: a DECLARE sorted ahead of the PUB_AT (its
    identifier is lower) would come before the CAN-ECB knows the node publishes, and be
    ignored."""
    w = Wire()
    w.join()
    a = w.node.advertise(A, 8, w.now)
    w.bind(a, 0x20, A)
    assert w.node.declare(a, 2, 100, 50, 0, w.now) == 0
    w.tick(1)  # the DECLARE goes
    w.feed(p.Grant(0x20, 5, 0x02))
    w.tick(500)  # the verdict wait
    assert w.node.declaration_state(a) == 2
    mark = len(w.sent)
    w.feed(p.Hello(1))
    w.tick(10, drain=False)  # the controller is busy for 10 ms
    for _ in range(20):
        w.drain()
        w.tick(1)
    sent = w.mgmt(mark)
    claim = sent.index(p.Request(p.CLAIM, 5, w.node_id))
    pub_at = sent.index(p.Holds(True, 5, 0x20, A))
    declare = sent.index(p.Declare(5, 0x20, 2, 100, 50, 0))
    assert claim < pub_at < declare


def test_an_assign_of_its_own_txnode_makes_it_announce() -> None:
    """Assign(t, its id) with its own TxNode t: a join under its id was assigned t, and the
    CAN-ECB forgot t's channels; the node reports them again (CLAIM, SUB_AT/PUB_AT), as after
    a Hello. It stays at t."""
    w = Wire()
    w.join()
    a = w.node.advertise(A, 8, w.now)
    w.bind(a, 0x20, A)
    w.tick(1100)  # past the announcement gap
    mark = len(w.sent)
    w.feed(p.Assign(5, w.node_id))
    w.tick(10)
    assert p.Request(p.CLAIM, 5, w.node_id) in w.mgmt(mark)
    assert p.Holds(True, 5, 0x20, A) in w.mgmt(mark)
    assert w.node.counters()["moves"] == 0


# --- real-time declarations -----------------------------------------------------------------


def _declared(w: Wire) -> int:
    """A published channel bound to 0x20, its DECLARE sent."""
    w.join()
    a = w.node.advertise(A, 8, w.now)
    w.bind(a, 0x20, A)
    assert w.node.declare(a, 2, 100, 50, 0, w.now) == 0
    w.tick(1)
    assert w.mgmt()[-1] == p.Declare(5, 0x20, 2, 100, 50, 0)
    return a


def _priority(w: Wire, channel: int) -> int:
    """The priority of the channel's next event."""
    mark = len(w.sent)
    assert w.node.publish(channel, b"x") == 0
    w.drain()
    ((can_id, _),) = w.events(mark)
    return int(can_id >> 21)


def test_the_answer_to_a_declaration_is_the_latest_verdict_once_it_stood_half_a_second() -> None:
    """A forged Grant before the CAN-ECB's Refuse is not the answer: the answer is the latest
    verdict since the DECLARE once it stood 0.5 s (verdict wait) with no other, and the node
    publishes at its former priority until then. It stops repeating DECLARE at the first
    verdict."""
    w = Wire()
    a = _declared(w)
    w.feed(p.Grant(0x20, 5, 0x02))  # forged
    mark = len(w.sent)
    w.tick(100)
    w.feed(p.Refuse(0x20, 5, 0x30, 7, 900))  # the CAN-ECB's
    w.tick(490)
    assert w.node.declaration_state(a) == 1
    assert _priority(w, a) == 0x80
    w.tick(20)
    assert ERRORS[w.node.declaration_state(a)] == "REFUSED"
    assert _priority(w, a) == 0x80
    w.tick(2000)
    assert not any(isinstance(m, p.Declare) for m in w.mgmt(mark))  # not repeated
    w.feed(p.Grant(0x20, 5, 0x02))  # a declaration whose answer is a Refuse is over
    w.tick(600)
    assert ERRORS[w.node.declaration_state(a)] == "REFUSED"
    assert _priority(w, a) == 0x80


def test_a_node_takes_verdicts_only_for_a_stream_it_declared() -> None:
    """A Grant for the node's channel before its DECLARE went out, or for another TxNode, is
    stray: it changes nothing."""
    w = Wire()
    w.join()
    a = w.node.advertise(A, 8, w.now)
    w.bind(a, 0x20, A)
    w.feed(p.Grant(0x20, 5, 0x02))  # nothing declared
    assert w.node.declare(a, 2, 100, 50, 0, w.now) == 0
    w.feed(p.Grant(0x20, 5, 0x03))  # declared, but its DECLARE is not sent yet
    w.feed(p.Grant(0x20, 6, 0x04))  # another TxNode's stream
    w.tick(600)
    assert w.node.declaration_state(a) == 1
    assert _priority(w, a) == 0x80
    assert p.Declare(5, 0x20, 2, 100, 50, 0) in w.mgmt()


def test_a_declared_stream_follows_the_latest_verdict() -> None:
    """Once granted, a Grant sets the stream's priority (also unasked) and a Refuse puts the
    channel back to its priority from before the declaration, until a Grant comes."""
    w = Wire()
    a = _declared(w)
    w.feed(p.Grant(0x20, 5, 0x10))
    w.tick(500)
    assert w.node.declaration_state(a) == 2
    assert _priority(w, a) == 0x10
    w.feed(p.Refuse(0x20, 5, 0x30, 7, 900))
    assert _priority(w, a) == 0x80
    w.feed(p.Grant(0x20, 5, 0x12))  # unasked: another declaration moved it
    assert _priority(w, a) == 0x12


# --- transfers ------------------------------------------------------------------------------


def test_a_transfer_does_not_overtake_the_one_before_it_on_its_etag() -> None:
    """The frames of one etag go in order: a transfer published after its channel's priority
    changed (ups_set_priority, or a Grant that another declaration caused) must not overtake
    the frames of the previous one still queued (the receiver would take its first frame as
    the end of the transfer in progress: lost)."""
    w = Wire()
    w.join()
    a = w.node.advertise(A, 1000, w.now)
    w.bind(a, 0x3400, A)
    w.tick(200)
    first, second = bytes(range(200)), bytes(100)
    assert w.node.publish(a, first) == 0  # 30 frames, all queued
    sending = w.node.tx()
    w.sent += [next(sending) for _ in range(3)]  # its first frames are on the bus
    w.feed(p.Grant(0x3400, 5, 0x10))  # unasked: another declaration moved this stream
    published = [first] + ([second] if w.node.publish(a, second) == 0 else [])
    for _ in range(100):
        w.drain()
    rx = t.Reassembler()
    got = []
    for can_id, data in w.events():
        event = rx.feed((5, can_id & p.ETAG_MASK), data, False, 1024, 0.0)
        if event is not None:
            got.append(event)
    assert got == published and rx.lost == 0


def test_a_transfer_begun_before_a_contradiction_is_not_finished_as_another_channel() -> None:
    """Frames of a transfer on etag E that began while E was channel A's and end once E is
    channel B's are not an event of B."""
    w = Wire()
    w.join()
    a = w.node.subscribe(A, w.now)
    b = w.node.subscribe(B, w.now)
    w.bind(a, 0x3000, A)
    frames = t.segment(bytes(range(30)), 4, 8)  # 5 frames
    can_id = p.make_id(0x80, 9, 0x3000)
    for data in frames[:2]:
        assert w.feed_raw(can_id, data) is None
    for _ in range(5):  # the CAN-ECB's answer for B (doubted at first: 0x3000 was A's)
        w.feed(p.Bind(0x3000, B))
        w.tick(60)
    assert w.node.channel_etag(b) == 0x3000
    delivered = [w.feed_raw(can_id, data) for data in frames[2:]]
    assert delivered == [None, None, None]


# --- what ups.h promises a port besides (issue 39) -------------------------------------------

HEADER = (Path(__file__).resolve().parent.parent / "c" / "ups.h").read_text()


def header_constant(name: str) -> int:
    found = re.search(rf"^#define {name} (-?\d+)\b", HEADER, re.MULTILINE)
    assert found, name
    return int(found.group(1))


def test_the_state_constants_are_the_numbers_the_calls_return() -> None:
    for names in (
        ("UPS_JOIN_NOT_STARTED", "UPS_JOIN_JOINING", "UPS_JOIN_JOINED"),
        ("UPS_CHANNEL_FREE", "UPS_CHANNEL_WAITING", "UPS_CHANNEL_BOUND"),
        ("UPS_DECL_NONE", "UPS_DECL_WAITING", "UPS_DECL_GRANTED"),
    ):
        assert [header_constant(name) for name in names] == [0, 1, 2]
    w = Wire()
    assert w.node.join_state == header_constant("UPS_JOIN_NOT_STARTED")
    w.node.start(w.now)
    assert w.node.join_state == header_constant("UPS_JOIN_JOINING")
    w.join()
    assert w.node.join_state == header_constant("UPS_JOIN_JOINED")
    a = w.node.subscribe(A, w.now)
    assert w.node.channel_state(a) == header_constant("UPS_CHANNEL_WAITING")
    w.bind(a, 0x20, A)
    assert w.node.channel_state(a) == header_constant("UPS_CHANNEL_BOUND")
    assert w.node.channel_state(5) == header_constant("UPS_CHANNEL_FREE")


def test_a_grants_priority_is_read_with_ups_channel_priority() -> None:
    w = Wire()
    w.join()
    a = w.node.advertise(A, 8, w.now)
    assert w.node.channel_priority(a) == 0x80
    w.bind(a, 0x20, A)
    assert w.node.declare(a, 2, 100, 50, 0, w.now) == 0
    w.tick(1)
    w.feed(p.Grant(0x20, 5, 0x11))
    w.tick(600)  # the answer once it stood 0.5 s
    assert w.node.declaration_state(a) == header_constant("UPS_DECL_GRANTED")
    assert w.node.channel_priority(a) == 0x11
    w.node.set_priority(a, 0x90)
    assert w.node.channel_priority(a) == 0x90
    assert w.node.channel_priority(7) == -1  # UPS_ERR_ARGUMENT: no such channel


def test_ups_idle_says_when_a_node_may_stop_ticking() -> None:
    w = Wire()
    idle = w.node.idle
    assert idle()  # not started
    w.node.start(w.now)
    assert not idle()  # joining
    w.join()
    assert idle()  # joined, nothing asked
    a = w.node.subscribe(A, w.now)
    assert not idle()  # the request is owed
    w.bind(a, 0x20, A)
    assert idle()
    w.feed(p.Hello(1))
    assert not idle()  # the answer to Hello is owed, then its second runs
    w.tick(1100)
    assert p.Holds(False, 5, 0x20, A) in w.mgmt()  # SUB_AT
    assert idle()
    w.node.unsubscribe(a)
    assert not idle()  # UNSUB is owed
    w.tick(1)
    assert idle()


def test_a_classic_only_build_takes_fd_frames_of_up_to_8_bytes() -> None:
    w = Wire(variant="min")
    assert w.node.config["fd"] == 0 and w.node.config["mtu"] == 8
    w.join()
    a = w.node.subscribe(A, w.now)
    w.bind(a, 0x20, A)
    event_id = (0x80 << 21) | (9 << 14) | 0x20
    got = w.feed_raw(event_id, b"\x01\x02\x03", FRAME_EXT | FRAME_FD)
    assert got == Event(a, b"\x01\x02\x03", 0x80, 9)
    before = w.node.counters()["foreign"]
    can_id, data = p.encode(p.Hello(1))
    w.feed_raw(can_id, data, FRAME_EXT | FRAME_FD)  # management frames are classic frames
    assert w.node.counters()["foreign"] == before + 1


def test_event_data_points_into_the_frame_fed() -> None:
    w = Wire()
    w.join()
    a = w.node.subscribe(A, w.now)
    w.bind(a, 0x20, A)
    assert w.feed_raw((0x80 << 21) | (9 << 14) | 0x20, b"\xaa\xbb") is not None
    pointer = ctypes.cast(w.node._event.data, ctypes.c_void_p).value
    assert pointer == ctypes.addressof(w.node._frame.data)  # not a copy: copy before reuse
