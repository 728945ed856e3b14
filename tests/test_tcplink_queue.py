"""The invariant of a link's event queue, on a real socket whose peer stops reading: every event
sent arrives whole and in order, or is counted as dropped; never a torn or reordered one."""

from __future__ import annotations

import asyncio
import socket

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ups import _tcpwire as w
from ups._tcplink import Link
from ups._tcpoutbox import SPLIT

SIZES = st.sampled_from([0, 8, 1000, SPLIT + 1, 200_000, 700_000])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    events=st.lists(st.tuples(SIZES, st.booleans()), min_size=1, max_size=40),
    limit=st.integers(1, 12),
    limit_bytes=st.sampled_from([300_000, 1 << 20, 64 << 20]),
    overflow=st.sampled_from(["drop_oldest", "drop_newest"]),
)
def test_every_event_arrives_whole_and_in_order_or_is_counted(
    events: list[tuple[int, bool]], limit: int, limit_bytes: int, overflow: str
) -> None:
    asyncio.run(_scenario(events, limit, limit_bytes, overflow))


async def _scenario(
    events: list[tuple[int, bool]], limit: int, limit_bytes: int, overflow: str
) -> None:
    loop = asyncio.get_running_loop()
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # the peer's window: small
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    listener.setblocking(False)
    client = socket.socket()
    client.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    client.setblocking(False)
    await loop.sock_connect(client, listener.getsockname())
    peer, _ = await loop.sock_accept(listener)
    listener.close()
    link = Link(
        lambda *a: None, lambda *a: None, lambda *a: None,
        limit=limit, limit_bytes=limit_bytes, overflow=overflow,  # type: ignore[arg-type]
    )  # fmt: skip
    await loop.create_connection(lambda: link.protocol, sock=client)
    sent: dict[int, bytes] = {}
    for seq, (size, yields) in enumerate(events, start=1):  # the peer reads nothing meanwhile
        data = seq.to_bytes(4, "big") * (size // 4) + bytes(size % 4)
        sent[seq] = data
        frame = (
            (w.event_header(7, size, 0x80, seq), data)
            if size > SPLIT
            else w.encode_event(7, data, 0x80, seq)
        )
        link.send(frame)
        if yields:
            await asyncio.sleep(0)  # the loop's turn: flushes, pauses
    link.close()  # writes what is queued once the peer reads, then closes
    received = bytearray()
    while chunk := await loop.sock_recv(peer, 1 << 20):
        received += chunk
    peer.close()
    await asyncio.wait_for(link.lost, 10)
    got = w.Decoder(max_frame=w.DEFAULT_MAX_FRAME).feed(received)
    seqs = [frame.seq for frame in got if isinstance(frame, w.Event)]
    assert len(seqs) == len(got)  # nothing but whole events
    assert seqs == sorted(set(seqs))  # in order, none twice
    for frame in got:
        assert isinstance(frame, w.Event) and frame.data == sent[frame.seq]  # whole
    assert len(seqs) + link.dropped == len(events)  # the rest is counted


def test_events_wait_in_the_queue_while_the_transport_is_paused() -> None:
    """A control frame that fills the transport pauses it: the events queued behind it stay in
    the link's bounded queue (counted, droppable), not copied into the transport's buffer."""
    asyncio.run(_paused_by_control())


async def _paused_by_control() -> None:
    loop = asyncio.get_running_loop()
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    listener.setblocking(False)
    client = socket.socket()
    client.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    client.setblocking(False)
    await loop.sock_connect(client, listener.getsockname())
    peer, _ = await loop.sock_accept(listener)
    listener.close()
    link = Link(lambda *a: None, lambda *a: None, lambda *a: None, limit=100)
    await loop.create_connection(lambda: link.protocol, sock=client)
    link.send_control(bytes(1 << 20))  # far above the transport's high-water mark
    for seq in range(1, 11):
        link.send(w.encode_event(7, b"12345678", 0x80, seq))
    flushed = loop.create_future()
    loop.call_soon(flushed.set_result, None)  # after the link's flush, queued before it
    await flushed
    try:
        assert link.queued == 10
    finally:
        link.abort("test over")
        peer.close()
