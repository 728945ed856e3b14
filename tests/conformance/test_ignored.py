"""Frames that get no answer: UNSUB, requests from a TxNode nobody holds, malformed management
frames and foreign frames ("Identifier layout", "Binding", "Restarts")."""

from __future__ import annotations

import can

from ups import name_to_uid
from ups.broker.can_ecb import CanEcb

from ._frames import (
    ECB,
    ECB_FRAMES,
    SUB_BIND,
    Bind,
    Frame,
    Hello,
    Malformed,
    decode,
    ident,
    sub_bind,
    unsub,
)
from ._wire import RawNode, Wire

PROBE = name_to_uid("conformance/probe")


async def probe(raw: Wire, node: RawNode) -> int:
    """Ask for the probe channel's binding; the log index of the Bind that answers."""
    assert node.txnode is not None
    since = raw.send(sub_bind(node.txnode, PROBE))
    i, _ = await raw.expect(lambda f: isinstance(f, Bind) and f.uid == PROBE, since=since)
    return i


async def test_unsub_gets_no_reply(raw: Wire, can_ecb: CanEcb) -> None:
    node = RawNode(raw, 0x7101)
    t = await node.join()
    uid = name_to_uid("conformance/unsub")
    await node.ask(SUB_BIND, uid)

    since = raw.send(unsub(t, uid))
    answered = await probe(raw, node)
    assert raw.heard(since, answered) == []
    # and the CAN-ECB still has nothing to say about it a while later
    await raw.expect_none(lambda f: isinstance(f, ECB_FRAMES), since=answered + 1, window=0.2)


async def test_request_from_a_txnode_nobody_holds_gets_no_bind(raw: Wire, can_ecb: CanEcb) -> None:
    node = RawNode(raw, 0x7102)
    t = await node.join()
    stray = 0x55
    assert stray != t
    uid = name_to_uid("conformance/stray")

    since = raw.send(sub_bind(stray, uid))
    await raw.expect_none(lambda f: isinstance(f, Bind) and f.uid == uid, since=since, window=0.5)
    # the CAN-ECB still answers the node that holds its TxNode
    await probe(raw, node)
    assert not raw.find(lambda f: isinstance(f, Bind) and f.uid == uid)


async def test_request_from_a_txnode_nobody_holds_brings_a_hello(
    raw: Wire, can_ecb: CanEcb, instance: int
) -> None:
    """ "any request from a TxNode that its table does not hold: ignored and counted; it sends
    Hello again (at most once per Hello gap)" - the Hello gap limits the Hellos sent "because
    of requests from unknown TxNodes", and this is the first such request."""
    node = RawNode(raw, 0x7104)
    await node.join()  # recovery is over
    since = raw.send(sub_bind(0x55, name_to_uid("conformance/stray")))
    await raw.expect(Hello(instance), since=since, timeout=2.0)


def _msg(identifier: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=identifier, data=data, is_extended_id=True)


def _not_a_probe_answer(frame: Frame) -> bool:
    if isinstance(frame, Bind):
        return frame.uid != PROBE
    return isinstance(frame, ECB_FRAMES)


async def _assert_ignored(raw: Wire, node: RawNode, frames: list[tuple[str, can.Message]]) -> None:
    """Send each frame, then a probe request: the CAN-ECB answers the probe, and nothing else."""
    answered: list[str] = []
    for what, msg in frames:
        since = raw.send(msg)
        await probe(raw, node)
        # answers may come late (a new binding is announced after its write): watch a while
        try:
            await raw.expect_none(_not_a_probe_answer, since=since, window=0.05, what=what)
        except AssertionError as exc:
            answered.append(str(exc))
    assert not answered, "\n".join(answered)
    await probe(raw, node)  # and it still answers


async def _joined(raw: Wire, node_id: int) -> tuple[RawNode, int]:
    node = RawNode(raw, node_id)
    return node, await node.join()


UID = name_to_uid("conformance/ignored").to_bytes(8, "big")
KNOCK_ID = ident(0, ECB, 0x3F00)


async def test_malformed_management_frames_are_ignored(raw: Wire, can_ecb: CanEcb) -> None:
    node, t = await _joined(raw, 0x7103)
    bound = await node.ask(SUB_BIND, name_to_uid("conformance/bound"))
    sub_bind_id = ident(0, t, SUB_BIND)
    malformed: list[tuple[str, can.Message]] = [
        ("SUB_BIND with 7 data bytes", _msg(sub_bind_id, UID[:7])),
        ("SUB_BIND without data", _msg(sub_bind_id, b"")),
        ("PUB_BIND with 4 data bytes", _msg(ident(0, t, 1), UID[:4])),
        ("CLAIM with 7 data bytes", _msg(ident(0, t, 4), UID[:7])),
        ("request etag 0x0000", _msg(ident(0, t, 0x0000), UID)),
        ("request etag 0x0007", _msg(ident(0, t, 0x0007), UID)),
        ("Roster with 7 data bytes", _msg(ident(0, t, 0x0006), UID[:7])),
        ("request etag 0x000F", _msg(ident(0, t, 0x000F), UID)),
        ("priority 0x80 at etag 0x0002", _msg(ident(0x80, t, SUB_BIND), UID)),
        ("priority 0x01 at etag 0x0002", _msg(ident(0x01, t, SUB_BIND), UID)),
        ("SUB_AT with 2 data bytes", _msg(ident(0, t, bound.etag), UID[:2])),
        ("Knock with a data byte", _msg(KNOCK_ID, b"\x00")),
        ("Knock with its low bits set", _msg(KNOCK_ID | 0x01, b"")),
        ("TxNode 0x7F at priority 0x80", _msg(ident(0x80, ECB, 0x3F00), b"")),
        ("status code 0xD", _msg(ident(0, ECB, 0x3D00), UID)),
        ("Uses of TxNode 0x7F", _msg(ident(0, ECB, 0x3A7F), UID)),
        ("Uses with 7 data bytes", _msg(ident(0, ECB, 0x3B01), UID[:7])),
        ("RosterEnd, done, with a next UID", _msg(ident(0, ECB, 0x3C81), UID)),
        ("Probe with 7 data bytes", _msg(ident(0, ECB, 0x3900), UID[:7])),
        ("Probe with its low bits set", _msg(ident(0, ECB, 0x3910), UID)),
        ("status code 0xE", _msg(ident(0, ECB, 0x3E00), b"")),
        ("Census with data", _msg(ident(0, ECB, 0x3000), UID)),
        ("Census with bits 4-7 set", _msg(ident(0, ECB, 0x3010), b"")),
        ("Hello with 4 data bytes", _msg(ident(0, ECB, 0x3300), UID[:4])),
        ("Serving with its low bits set", _msg(ident(0, ECB, 0x3601), UID)),
        ("Assign with bits 8-11 set", _msg(ident(0, ECB, 0x2F05), UID)),
        ("Offer with bits 8-11 set", _msg(ident(0, ECB, 0x2185), UID)),
        ("Offer with 7 data bytes", _msg(ident(0, ECB, 0x2085), UID[:7])),
        ("Stage with data", _msg(ident(0, ECB, 0x0000), b"\x00")),
        ("Query whose data disagrees", _msg(ident(0, ECB, 0x1005), bytes([0x60]) + UID[1:])),
        ("Bind with 7 data bytes", _msg(ident(1, ECB, bound.etag), UID[:7])),
        ("Bind at etag 0x0005", _msg(ident(1, ECB, 0x0005), UID)),
    ]
    for what, msg in malformed:
        assert isinstance(decode(msg), Malformed), what
    await _assert_ignored(raw, node, malformed)


async def test_foreign_frames_are_ignored(raw: Wire, can_ecb: CanEcb) -> None:
    """11-bit identifiers, remote frames and error frames."""
    node, t = await _joined(raw, 0x7105)
    sub_bind_id = ident(0, t, SUB_BIND)
    foreign: list[tuple[str, can.Message]] = [
        ("11-bit frame", can.Message(arbitration_id=0x002, data=UID, is_extended_id=False)),
        ("11-bit frame 0x7FF", can.Message(arbitration_id=0x7FF, is_extended_id=False)),
        ("remote SUB_BIND", can.Message(arbitration_id=sub_bind_id, is_remote_frame=True, dlc=8)),
        ("remote Knock", can.Message(arbitration_id=KNOCK_ID, is_remote_frame=True, dlc=0)),
        ("error frame", can.Message(arbitration_id=KNOCK_ID, is_error_frame=True)),
    ]
    await _assert_ignored(raw, node, foreign)


async def test_can_fd_frames_are_ignored(raw: Wire, can_ecb: CanEcb) -> None:
    """ "Management frames are classic frames: a CAN FD frame there is foreign.\""""
    node, t = await _joined(raw, 0x7106)
    fd: list[tuple[str, can.Message]] = [
        (
            "CAN FD SUB_BIND",
            can.Message(arbitration_id=ident(0, t, SUB_BIND), data=UID, is_fd=True),
        ),
        ("CAN FD Knock", can.Message(arbitration_id=KNOCK_ID, is_fd=True)),
    ]
    await _assert_ignored(raw, node, fd)
