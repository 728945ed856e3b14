"""The gateway's tap (gateway/_tap.py) on a real python-can virtual bus: a new publisher's
first events, sent the moment its binding is announced, are kept until the gateway forwards
the channel, handed over in order, and never forwarded twice once the CAN face has the etag."""

from __future__ import annotations

import can

from ups import _canproto as p
from ups import name_to_uid
from ups._canlink import CanLink
from ups.gateway._tap import TAP_ETAGS, TAP_FRAMES, Tap

from .conftest import eventually, send_management

UID = name_to_uid("tap/speed")
ETAG = 0x0123
PUBLISHER, GATEWAY = 0x05, 0x09


def _event(raw: can.BusABC, data: bytes, txnode: int = PUBLISHER) -> None:
    can_id = p.make_id(0x80, txnode, ETAG)
    raw.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))


async def test_what_the_tap_keeps_goes_first_then_the_face_takes_over(
    bus: str, raw_bus: can.BusABC
) -> None:
    link = CanLink.open(bus)
    counters: dict[str, int] = {}
    forwarded: list[bytes] = []
    face_has: set[int] = set()
    tap = Tap(link, forwarding=lambda uid: False, receives=face_has.__contains__,
              own=lambda: GATEWAY, counters=counters)  # fmt: skip
    tap.start()
    tap.wide(True)
    link.start()
    try:
        send_management(raw_bus, p.Bind(ETAG, UID))  # the publisher's binding ...
        for n in range(3):  # ... and its first events, before the gateway decided
            _event(raw_bus, bytes([n]))
        _event(raw_bus, b"\xee", txnode=GATEWAY)  # the gateway's own frame: never tapped
        send_management(raw_bus, p.Bind(0x0124, name_to_uid("tap/other")))  # not its etag
        await eventually(lambda: sum(len(t.frames) for t in tap._taps.values()) == 3)
        tap.forward(UID, lambda data, priority: forwarded.append(data))
        assert forwarded == [b"\x00", b"\x01", b"\x02"]
        _event(raw_bus, b"\x03")  # forwarded by the tap while the face binds
        await eventually(lambda: len(forwarded) == 4)
        face_has.add(ETAG)  # the face relies on the etag now: from here on, the face's
        _event(raw_bus, b"\x04")
        await eventually(lambda: ETAG not in tap._taps)
        assert forwarded == [b"\x00", b"\x01", b"\x02", b"\x03"] and counters["tapped"] == 4
    finally:
        tap.close()
        link.close()


async def test_the_tap_is_bounded(bus: str, raw_bus: can.BusABC) -> None:
    link = CanLink.open(bus)
    counters: dict[str, int] = {}
    tap = Tap(link, forwarding=lambda uid: False, receives=lambda etag: False,
              own=lambda: GATEWAY, counters=counters)  # fmt: skip
    tap.start()
    tap.wide(True)
    link.start()
    try:
        send_management(raw_bus, p.Holds(True, PUBLISHER, ETAG, UID))  # a PUB_AT starts it too
        for n in range(TAP_FRAMES + 10):
            _event(raw_bus, n.to_bytes(2, "big"))
        await eventually(lambda: counters["tap_dropped"] == 10)
        tap.drop(UID)  # nobody wanted it
        assert not tap._taps
        for n in range(TAP_ETAGS + 1):  # one etag more than it taps at once: counted
            send_management(raw_bus, p.Bind(0x0200 + n, name_to_uid(f"tap/{n}")))
        await eventually(lambda: counters["tap_full"] == 1)
        assert len(tap._taps) == TAP_ETAGS
    finally:
        tap.close()
        link.close()
