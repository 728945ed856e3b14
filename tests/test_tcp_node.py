"""TCP/IP nodes and the TCP-ECB in one process, on real loopback sockets."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from ups import BrokerUnavailable, Closed, ConfigError, Node, PayloadTooLarge, name_to_uid
from ups import _tcpwire as w
from ups._tcpface import HEARTBEAT, parse_address, query_status
from ups.broker.tcp_ecb import TcpEcb

from .conftest import eventually


@contextlib.asynccontextmanager
async def running_tcp_ecb(port: int = 0, **options: Any) -> AsyncIterator[TcpEcb]:
    options.setdefault("recovery", 0)
    ecb = TcpEcb("127.0.0.1", port, **options)
    await ecb.start()
    try:
        yield ecb
    finally:
        await ecb.close()


@pytest.fixture
async def tcp_ecb() -> AsyncIterator[TcpEcb]:
    async with running_tcp_ecb() as ecb:
        yield ecb


def addr(ecb: TcpEcb) -> str:
    return f"127.0.0.1:{ecb.port}"


def stalled_subscriber() -> socket.socket:
    """A listening socket for a subscriber that never reads (the kernel accepts for it), with
    a small receive buffer, so that its publishers' queues fill at once."""
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.bind(("127.0.0.1", 0))
    stalled.listen()
    return stalled


@contextlib.asynccontextmanager
async def registered_at(
    ecb: TcpEcb, node_id: int, address: tuple[str, int], *subscribed: int
) -> AsyncIterator[Callable[[w.Frame], None]]:
    """Register a node at ``address`` (say a :func:`stalled_subscriber`) with the TCP-ECB, as
    subscribing to the ``subscribed`` UIDs, and keep it alive as a node does: a Ping every
    HEARTBEAT, what the ECB sends read and dropped. However long the test runs, the ECB never
    takes it for dead (it would after ``liveness`` s of silence, then tell its publishers).
    Yields a function that sends the ECB more frames from it."""
    reader, writer = await asyncio.open_connection("127.0.0.1", ecb.port)
    hello = w.Hello(node_id, "registered", *address)
    writer.write(b"".join(w.encode(f) for f in (hello, *(w.Subscribe(u) for u in subscribed))))

    async def ping() -> None:
        while True:
            writer.write(w.encode(w.Ping()))
            await asyncio.sleep(HEARTBEAT)  # a node's pace of Pings, not a wait for anything

    async def drain() -> None:
        while await reader.read(1 << 16):
            pass

    tasks = [asyncio.create_task(ping()), asyncio.create_task(drain())]
    try:
        yield lambda frame: writer.write(w.encode(frame))
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


def tcp_node(ecb: TcpEcb, name: str, **options: Any) -> Node:
    options.setdefault("node_id", hash(name) & 0xFFFF_FFFF_FFFF)
    return Node(broker=addr(ecb), name=name, **options)


async def test_publish_reaches_local_and_remote_subscribers(tcp_ecb: TcpEcb) -> None:
    async with (
        tcp_node(tcp_ecb, "pub") as pub,
        tcp_node(tcp_ecb, "sub1") as sub1,
        tcp_node(tcp_ecb, "sub2") as sub2,
    ):
        local = await pub.subscribe("speed")
        remote1 = await sub1.subscribe("speed")
        remote2 = await sub2.subscribe("speed", "other")
        pub.set_priority("speed", 0x42)
        await pub.publish("speed", b"\x01\x02")
        for sub in (local, remote1, remote2):
            msg = await sub.get_msg(timeout=5)
            assert (msg.data, msg.channel.name, msg.priority) == (b"\x01\x02", "speed", 0x42)
        assert (local.pending, remote1.pending, remote2.pending) == (0, 0, 0)
        assert pub.stats()["sent"] == 2  # one copy per subscribing node, none for itself
        assert sub1.stats()["received"] == sub2.stats()["received"] == 1


async def test_source_is_the_publishers_node_id(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "a", node_id=0xA1) as a, tcp_node(tcp_ecb, "b") as b:
        sub = await b.subscribe("x")
        await a.publish("x", b"")
        assert (await sub.get_msg(timeout=5)).source == 0xA1


async def test_unsubscribe_stops_delivery_and_leaves_the_ecb_lists(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "sub") as node:
        sub = await node.subscribe("x")
        await pub.publish("x", b"1")
        await sub.get_msg(timeout=5)
        await sub.close()
        uid = sub.channels[0].uid
        await eventually(lambda: uid not in tcp_ecb._subscribers)
        await eventually(lambda: not pub.face.stats()["peers"])  # its link was closed
        again = await node.subscribe("other")
        await pub.publish("x", b"2")
        await pub.publish("other", b"3")
        assert (await node.get_msg(timeout=5)).data == b"3"  # and "2" was never sent
        assert again.pending == 0
        assert node.stats()["unsubscribed"] == 0


async def test_a_subscriber_joining_later_is_told_to_the_publisher(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "pub") as pub:
        await pub.publish("x", b"nobody")
        assert pub.stats()["sent"] == 0
        async with tcp_node(tcp_ecb, "late") as late:
            sub = await late.subscribe("x")
            await eventually(lambda: bool(pub.face._outbox._targets))
            await pub.publish("x", b"you")
            assert (await sub.get_msg(timeout=5)).data == b"you"
            assert tcp_ecb.counters["pushes"] == 1


async def test_node_close_withdraws_everything_and_leaves_at_once(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "pub") as pub:
        await pub.publish("x", b"")
        async with tcp_node(tcp_ecb, "sub") as node:
            await node.subscribe("x")
            await eventually(lambda: bool(pub.face._outbox._targets))
        await eventually(lambda: not pub.face._outbox._targets)
        await eventually(lambda: len(tcp_ecb._members) == 1)
    await eventually(lambda: not tcp_ecb._members)
    assert tcp_ecb.counters["left"] == 2


async def test_events_queued_before_a_peer_is_reached_are_delivered_at_close(
    tcp_ecb: TcpEcb,
) -> None:
    async with tcp_node(tcp_ecb, "sub") as node:
        sub = await node.subscribe("x")
        async with tcp_node(tcp_ecb, "pub") as pub:
            for i in range(3):
                await pub.publish("x", bytes([i]))  # the link to "sub" is still being dialled
        got = [(await sub.get_msg(timeout=5)).data for _ in range(3)]
        assert got == [b"\x00", b"\x01", b"\x02"]


async def test_events_keep_flowing_while_the_ecb_is_down(tcp_ecb: TcpEcb) -> None:
    port = tcp_ecb.port
    async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "sub") as node:
        sub = await node.subscribe("x")
        await pub.publish("x", b"before")
        assert (await sub.get_msg(timeout=5)).data == b"before"
        await tcp_ecb.close()
        await eventually(lambda: not pub.stats()["broker_connected"])
        await pub.publish("x", b"during")
        assert (await sub.get_msg(timeout=5)).data == b"during"
        async with running_tcp_ecb(port, recovery=0.3) as ecb:
            await eventually(lambda: pub.stats()["reconnects"] == node.stats()["reconnects"] == 1)
            await eventually(lambda: not ecb._recovering)
            uid = sub.channels[0].uid
            assert ecb._subscribers[uid] == {node.node_id}
            assert ecb._publishers[uid] == {pub.node_id}
            await pub.publish("x", b"after")
            assert (await sub.get_msg(timeout=5)).data == b"after"
            async with tcp_node(ecb, "new") as new:
                sub2 = await new.subscribe("x")
                await eventually(lambda: len(pub.face._outbox._targets[uid]) == 2)
                await pub.publish("x", b"both")
                assert (await sub2.get_msg(timeout=5)).data == b"both"
                assert (await sub.get_msg(timeout=5)).data == b"both"


async def test_a_restarted_ecb_tells_no_publisher_a_half_built_list() -> None:
    async with running_tcp_ecb() as first:
        port = first.port
        pub_node = tcp_node(first, "pub")
        sub_node = tcp_node(first, "sub")
        async with pub_node as pub, sub_node as node:
            sub = await node.subscribe("x")
            await pub.publish("x", b"0")
            await sub.get_msg(timeout=5)
            await first.close()
            # The publisher re-registers first; the subscriber is kept away for a while.
            node.face.broker = ("127.0.0.1", 1)  # type: ignore[attr-defined]
            async with running_tcp_ecb(port, recovery=0.5) as second:
                await eventually(lambda: pub.stats()["reconnects"] == 1)
                sent = pub.stats()["sent"]
                await pub.publish("x", b"1")
                assert pub.stats()["sent"] == sent + 1  # still sent to the subscriber
                assert (await sub.get_msg(timeout=5)).data == b"1"
                node.face.broker = ("127.0.0.1", port)  # type: ignore[attr-defined]
                await eventually(lambda: node.stats()["reconnects"] == 1)
                await eventually(lambda: not second._recovering)
                await pub.publish("x", b"2")
                assert (await sub.get_msg(timeout=5)).data == b"2"


async def test_a_silent_node_leaves_every_list_after_the_liveness_timeout() -> None:
    async with running_tcp_ecb(liveness=1.0) as ecb, tcp_node(ecb, "pub") as pub:
        await pub.publish("x", b"")
        with socket.create_connection(("127.0.0.1", ecb.port)) as raw:
            raw.sendall(w.encode(w.Hello(0xDEAD, "zombie", "127.0.0.1", 9)))
            raw.sendall(w.encode(w.Subscribe(pub.face._advertised.copy().pop())))  # type: ignore[attr-defined]
            peers = pub.face._outbox._peers  # type: ignore[attr-defined]
            await eventually(lambda: 0xDEAD in {p.node_id for p in peers.values()})
            # it never pings, and keeps its connection open
            await eventually(lambda: 0xDEAD not in ecb._members, timeout=3)
            await eventually(lambda: not pub.face._outbox._peers)  # type: ignore[attr-defined]
            assert ecb.counters["left"] == 1


async def test_silent_publishers_leave_one_after_the_other() -> None:
    """A publisher that goes silent with its registrations still in place (killed, say) leaves
    every list, and the sweep that removed it goes on to remove the next one."""
    async with running_tcp_ecb(liveness=1.0) as ecb, tcp_node(ecb, "sub") as sub:
        await sub.subscribe("x")
        uid = name_to_uid("x")
        for zombie in (0xDEAD, 0xBEEF):
            with socket.create_connection(("127.0.0.1", ecb.port)) as raw:
                raw.sendall(w.encode(w.Hello(zombie, "zombie", "127.0.0.1", 9)))
                raw.sendall(w.encode(w.Advertise(uid)) + w.encode(w.Subscribe(uid)))
                await eventually(lambda z=zombie: z in ecb._publishers.get(uid, ()))
                await eventually(lambda z=zombie: z not in ecb._members, timeout=3)
        assert ecb.counters["left"] == 2 and ecb.counters["errors"] == 0
        assert ecb._publishers.get(uid) is None and ecb._subscribers[uid] == {sub.node_id}


async def test_a_node_that_lost_its_link_leaves_after_the_liveness_timeout() -> None:
    async with running_tcp_ecb(liveness=1.0) as ecb:
        raw = socket.create_connection(("127.0.0.1", ecb.port))
        raw.sendall(w.encode(w.Hello(0xBEEF, "crash", "127.0.0.1", 9)) + w.encode(w.Subscribe(1)))
        await eventually(lambda: 1 in ecb._subscribers)
        raw.close()  # without withdrawing: as if killed
        await eventually(
            lambda: ecb._members.get(0xBEEF) is not None and not ecb._members[0xBEEF].link
        )
        assert 1 in ecb._subscribers  # it may come back within the timeout...
        await eventually(lambda: 1 not in ecb._subscribers, timeout=3)  # ...it did not


async def test_a_node_back_under_the_same_id_keeps_only_what_it_registers_again(
    tcp_ecb: TcpEcb,
) -> None:
    def hello_and(*frames: w.Frame) -> bytes:
        return b"".join(w.encode(f) for f in (w.Hello(7, "n", "127.0.0.1", 9), *frames))

    with (
        socket.create_connection(("127.0.0.1", tcp_ecb.port)) as first,
        socket.create_connection(("127.0.0.1", tcp_ecb.port)) as second,
    ):
        first.sendall(hello_and(w.Subscribe(1), w.Subscribe(2), w.Advertise(3)))
        await eventually(lambda: {1, 2} <= set(tcp_ecb._subscribers) and 3 in tcp_ecb._publishers)
        second.sendall(hello_and(w.Subscribe(2), w.Ping()))
        await eventually(lambda: set(tcp_ecb._subscribers) == {2} and not tcp_ecb._publishers)
        # The ECB cut the old link: past what it had sent, it reads to EOF or a reset, at once.
        first.settimeout(2)
        with contextlib.suppress(ConnectionResetError):
            while first.recv(1 << 16):
                pass


async def test_a_stalled_subscriber_costs_only_its_own_events(tcp_ecb: TcpEcb) -> None:
    with stalled_subscriber() as stalled:
        host, port = stalled.getsockname()
        async with (
            tcp_node(tcp_ecb, "pub", peer_queue=1000, peer_overflow="drop_newest") as pub,
            tcp_node(tcp_ecb, "fast") as fast,
        ):
            sub = await fast.subscribe("x", maxlen=100_000)
            async with registered_at(tcp_ecb, 0x51, (host, port), sub.channels[0].uid):
                await pub.publish("x", b"")  # advertise
                targets = pub.face._outbox._targets  # type: ignore[attr-defined]
                await eventually(lambda: len(targets.get(sub.channels[0].uid, ())) == 2)
                payload = bytes(1000)
                count = 20_000
                for i in range(count):
                    await pub.publish("x", payload)
                    if i % 10 == 0:  # the fast subscriber runs in this loop too
                        await asyncio.sleep(0)
                for _ in range(count + 1):
                    await sub.get_msg(timeout=5)
                stats = pub.stats()
                assert stats["peer_dropped"] > 0
                assert stats["peer_dropped"] + 1000 < count  # what the kernel took was not lost
                peers = pub.face.status()["peers"]  # type: ignore[attr-defined]
                by_id = {p["node_id"]: p for p in peers}
                assert by_id["0x0000000000000051"]["dropped"] == stats["peer_dropped"]
                assert by_id[f"0x{fast.node_id:016x}"]["dropped"] == 0


async def test_a_stalled_subscriber_that_leaves_keeps_its_drops_counted(tcp_ecb: TcpEcb) -> None:
    """Its publisher lets it go and gives what is queued for it a moment to go out (it does
    not: 2 s); all that while, what was dropped for it is counted, and then what was left."""
    uid = name_to_uid("x")
    with stalled_subscriber() as stalled:
        async with tcp_node(tcp_ecb, "pub", peer_queue=100) as pub:
            outbox = pub.face._outbox  # type: ignore[attr-defined]
            async with registered_at(tcp_ecb, 0x53, stalled.getsockname(), uid) as send:
                await pub.advertise("x")
                await eventually(lambda: pub.stats()["peers"] == 1)  # its link is up
                for _ in range(50):  # until the kernel's buffers and the queue are full
                    for _ in range(1000):
                        await pub.publish("x", bytes(1000))
                    if pub.stats()["peer_dropped"]:
                        break
                dropped = pub.stats()["peer_dropped"]
                assert dropped > 0
                send(w.Unsubscribe(uid))
                await eventually(lambda: 0x53 not in outbox._peers)  # let go: its link closes
                assert outbox._closing  # (still closing, and its count...)
                assert pub.stats()["peer_dropped"] >= dropped  # ...is there all the same
                await eventually(lambda: not outbox._closing)
                assert pub.stats()["peer_dropped"] > dropped  # and what was queued: dropped


async def test_drops_stay_counted_when_the_link_is_lost_and_dialled_again(
    tcp_ecb: TcpEcb,
) -> None:
    """A subscriber's link is reset and its publisher dials it again: what was dropped for it
    on the lost link stays in ``peer_dropped`` (and in its row of the status), and what is
    dropped on the new link adds to it (mutation audit, issue 41: the lost link's count
    vanished at the redial)."""
    uid = name_to_uid("x")
    loop = asyncio.get_running_loop()
    with stalled_subscriber() as stalled:
        stalled.setblocking(False)
        async with (
            tcp_node(tcp_ecb, "pub", peer_queue=100) as pub,
            registered_at(tcp_ecb, 0x54, stalled.getsockname(), uid),
        ):
            await pub.advertise("x")
            first, _ = await asyncio.wait_for(loop.sock_accept(stalled), 10)
            with first:
                for _ in range(50):  # until the kernel's buffers and the queue are full
                    for _ in range(1000):
                        await pub.publish("x", bytes(1000))
                    if pub.stats()["peer_dropped"]:
                        break
                dropped = pub.stats()["peer_dropped"]
                assert dropped > 0
                # closed with a reset (linger on, 0 s): the link is lost, not ended
                first.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            second, _ = await asyncio.wait_for(loop.sock_accept(stalled), 10)  # redialled
            with second:
                assert pub.stats()["peer_dropped"] >= dropped
                (row,) = pub.face.status()["peers"]  # type: ignore[attr-defined]
                assert row["dropped"] == pub.stats()["peer_dropped"]
                for _ in range(50):  # the new link fills up too: its drops add up
                    for _ in range(1000):
                        await pub.publish("x", bytes(1000))
                    if pub.stats()["peer_dropped"] > dropped:
                        break
                assert pub.stats()["peer_dropped"] > dropped


async def test_a_peer_link_that_breaks_is_dialled_again(
    tcp_ecb: TcpEcb,
) -> None:
    async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "sub") as node:
        sub = await node.subscribe("x")
        await pub.publish("x", b"1")
        await sub.get_msg(timeout=5)
        (peer,) = pub.face._outbox._peers.values()  # type: ignore[attr-defined]
        old = peer.link
        for link in list(node.face._inbox._links):  # type: ignore[attr-defined]
            link.abort("test")
        # Until the publisher sees the reset, what it writes is lost in the dead socket.
        await eventually(lambda: peer.link is not old and peer.link.transport is not None)
        await pub.publish("x", b"2")
        assert (await sub.get_msg(timeout=5)).data == b"2"


async def test_join_without_an_ecb_times_out_clearly() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here
    node = Node(broker=f"127.0.0.1:{port}", join_timeout=0.3)
    with pytest.raises(BrokerUnavailable, match=f"nothing listened at 127.0.0.1:{port} within"):
        await node.start()
    await node.close()


async def test_a_late_ecb_is_waited_for() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    node = Node(broker=f"127.0.0.1:{port}", join_timeout=10)
    starting = asyncio.ensure_future(node.start())
    await asyncio.sleep(0.2)
    assert not starting.done()
    async with running_tcp_ecb(port):
        await starting
        await node.close()


async def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ConfigError, match="one network"):
        Node(can="virtual:x", broker="127.0.0.1:1")
    with pytest.raises(ConfigError, match="one network"):
        Node()
    with pytest.raises(ConfigError, match="HOST:PORT"):
        await Node(broker="127.0.0.1:http").start()
    with pytest.raises(ConfigError, match="peer_queue"):
        await Node(broker="127.0.0.1:1", peer_queue=0).start()
    with pytest.raises(ConfigError, match="peer_overflow"):
        await Node(broker="127.0.0.1:1", peer_overflow="drop_all").start()  # type: ignore[arg-type]


def test_addresses_parse() -> None:
    assert parse_address("10.0.0.1:99") == ("10.0.0.1", 99)
    assert parse_address("example") == ("example", 7411)
    assert parse_address(":5") == ("127.0.0.1", 5)
    assert parse_address("[::1]:5") == ("::1", 5)
    for bad in ("h:-1", "h:65536", "h:x"):
        with pytest.raises(ConfigError):
            parse_address(bad)


async def test_oversized_payloads_are_refused(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "sub") as node:
        sub = await node.subscribe("big")
        limit = pub.face.max_payload
        await pub.publish("big", bytes(limit))
        assert len((await sub.get_msg(timeout=5)).data) == limit
        with pytest.raises(PayloadTooLarge, match=f"at most {limit}"):
            await pub.publish("big", bytes(limit + 1))


async def test_status_of_ecb_and_node(tcp_ecb: TcpEcb) -> None:
    async with tcp_node(tcp_ecb, "pub") as pub, tcp_node(tcp_ecb, "sub") as node:
        await node.subscribe("x")
        await pub.publish("x", b"")
        ecb_status = await query_status(addr(tcp_ecb))
        (channel,) = ecb_status["channels"]
        assert channel["subscribers"] == (f"0x{node.node_id:016x}",)
        assert channel["publishers"] == (f"0x{pub.node_id:016x}",)
        host, port = pub.face.address  # type: ignore[attr-defined]
        node_status = await query_status(f"{host}:{port}")
        assert node_status["stats"]["published"] == 1
        assert node_status["peers"][0]["node_id"] == f"0x{node.node_id:016x}"
    with pytest.raises(BrokerUnavailable):
        await query_status(f"127.0.0.1:{port}", timeout=1)


async def test_closed_node_refuses_work(tcp_ecb: TcpEcb) -> None:
    node = tcp_node(tcp_ecb, "n")
    await node.start()
    await node.close()
    with pytest.raises(Closed):
        await node.publish("x", b"")
