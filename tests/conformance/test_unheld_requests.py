"""A standing-by CAN-ECB and requests of TxNodes nobody holds ("Watching the one that serves"):
the one that serves rightly leaves them unanswered (it counts them, and says Hello at most once
per Hello gap), so a forger sending them now and then must not make ours take over: each
takeover would be a recovery window for the whole bus, and the roles would swap on and on.
The test plays the CAN-ECB that serves (a lower instance: it answers each Probe with its
Serving, and the forged requests with nothing but one Hello), and the forger."""

from __future__ import annotations

from ups import name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import MAX_TXNODE, Assign, Hello, Knock, Probe, Serving, pub_bind, sub_bind
from ._wire import RawNode, Wire

ANSWER = 2.5  #: Timers: "answer"
UID = name_to_uid("conformance/unheld")
FORGED = 4  #: forged requests, one per ANSWER + a little: about 10 s


async def _standing_by(raw: Wire, instance: int) -> tuple[RawNode, int]:
    """A joined node, then ours standing by for a lower instance that answers its Probes."""
    node = RawNode(raw, 0x5EC0)
    await node.join()

    def serve(frame: object) -> None:  # the other CAN-ECB: it answers each Probe
        if frame == Probe(instance):
            raw.send(Serving(0))

    raw.handlers.append(serve)
    since = raw.send(Serving(0))
    await raw.expect(Probe(instance), since=since, timeout=3.0)  # it stands by
    return node, since


async def test_requests_of_a_txnode_nobody_holds_do_not_make_it_take_over(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """SUB_BIND and PUB_BIND from a TxNode it never heard assigned, one every
    ANSWER + 0.1 s for about 10 s, none answered: ours stands by all along (no Hello)."""
    node, since = await _standing_by(raw, instance)
    forger = MAX_TXNODE if node.txnode != MAX_TXNODE else MAX_TXNODE - 1
    forged = [sub_bind(forger, UID), pub_bind(forger, UID + 1), pub_bind(forger, UID + 2)]
    for i in range(FORGED):
        asked = raw.send(forged[i % len(forged)])
        if i == 0:
            raw.send(Hello(0))  # the one that serves: Hello, at most once per Hello gap
        await raw.expect_none(Hello(instance), since=asked, window=ANSWER + 0.1,
                              what="it took over for a request nobody owes an answer")  # fmt: skip
    assert not raw.find(Serving(instance), since=since)


async def test_a_txnode_heard_assigned_is_watched_beside_the_forged_ones(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """Forged requests go on, and a node joins meanwhile (Knock, and the Assign of the one that
    serves): that node's SUB_BIND, unanswered, makes ours take over after the answer time, as
    before."""
    node, _ = await _standing_by(raw, instance)
    forger = MAX_TXNODE if node.txnode != MAX_TXNODE else MAX_TXNODE - 1
    joined = 0x40 if node.txnode != 0x40 else 0x41
    raw.send(sub_bind(forger, UID))
    raw.send(Knock(), Assign(joined, 0xB0B))  # a real join, answered
    await raw.expect_none(Hello(instance), since=raw.mark(), window=1.0)
    raw.send(pub_bind(forger, UID + 1))
    asked = raw.send(sub_bind(joined, UID + 3))  # owed: the one that serves assigned it
    i_hello, _ = await raw.expect(Hello(instance), since=asked, timeout=ANSWER + 1.0)
    assert raw.log[i_hello].at - raw.log[asked].at >= ANSWER - 0.01
