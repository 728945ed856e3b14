"""Issue 32: what a holder of a fleet certificate could still do with TLS and the ACL, kept as
tests (each failed before the change that made it pass).

- Right after a TCP-ECB restart it said Hello with legitimate nodes' ids before they came back,
  and so locked them out for the whole run: now the ACL may pin node ids to identities (refused
  to every other identity from the ECB's first moment), and the ECB keeps the bindings it made
  in a file across restarts (``broker/_identities.py``).
- A node's own listening port answered its Status to any fleet identity (the ACL's ``status``
  right was checked at the ECB only): now the ECB names, to every node after its Hello, the
  identities that may read it (``StatusReaders``), and the node answers no other, on its
  listening port or on its links to subscribers.
- A link the ECB vouched for on no channel sent a 1 MiB event: it is not read until the link
  is admitted (``ups/_tcpbounds.py``).

Real sockets and certificates made by ``ups certs``; the restart is of a real ``ups broker``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from pathlib import Path

import pytest

from ups import AccessDenied, ConfigError, Node, name_to_uid
from ups import _tcpwire as w
from ups._tcpface import query_status
from ups.broker import _identities
from ups.broker.tcp_ecb import TcpEcb

from .conftest import eventually
from .procs import Proc
from .test_acl import acl_ecb, fleet, node
from .test_tls import tls

__all__ = ["fleet"]  # the fixture, shared with test_acl


def opts(fleet: Path, name: str) -> list[str]:
    return ["--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(fleet / f"{name}.crt"),
            "--tls-key", str(fleet / f"{name}.key")]  # fmt: skip


async def _squat(fleet: Path, address: str, node_id: int) -> None:
    """mallory says Hello with ``node_id``: AccessDenied if the ECB refuses her."""
    squatter = Node(broker=address, node_id=node_id, join_timeout=5, tls=tls(fleet, "mallory"))
    try:
        await squatter.start()
    finally:
        await squatter.close()


# --- node ids pinned, and kept across restarts --------------------------------------------


async def test_a_pinned_node_id_is_refused_to_every_other_identity_from_the_first_moment(
    fleet: Path,
) -> None:
    async with acl_ecb(fleet) as ecb:  # bob (0xb0 pinned to him) has never been here
        with pytest.raises(AccessDenied, match="node id 00000000000000b0 is taken"):
            await _squat(fleet, f"127.0.0.1:{ecb.port}", 0xB0)
        assert ecb.stats()["impostors"] == 1 and ecb.stats()["nodes"] == 0
        async with node(fleet, ecb, "bob", 0xB0) as bob:
            await bob.publish("robot/speed", b"")


def test_a_restart_opens_no_window_to_squat_a_node_id(fleet: Path, tmp_path: Path) -> None:
    """alice's node (0xa1) is stopped while the TCP-ECB restarts; mallory says Hello with its
    id as soon as the new ECB listens. She is refused, and alice's node comes back and is
    served."""
    ids = tmp_path / "identities.json"

    def broker(listen: str) -> tuple[Proc, str]:
        proc = Proc("broker", "--listen", listen, "--recovery", "0", "--identities", str(ids),
                    "--acl", str(fleet / "acl.toml"), *opts(fleet, "broker"))  # fmt: skip
        line = proc.wait_for_line(r"TCP-ECB on 127\.0\.0\.1:\d+")
        return proc, line.split("TCP-ECB on ")[1].split()[0]

    first, address = broker("127.0.0.1:0")
    with first, Proc("sub", "robot/speed", "--broker", address, "--node-id", "0xa1", "--count",
                     "1", "--json", "--timeout", "60", *opts(fleet, "alice")) as alice:  # fmt: skip
        alice.wait_for_line("subscribed to")
        alice.pause()  # alice's node is down (restarting) while the ECB restarts
        try:
            first.stop()
            second, _ = broker(address)
            with second:
                with pytest.raises(AccessDenied, match="node id 00000000000000a1 is taken"):
                    asyncio.run(_squat(fleet, address, 0xA1))
                alice.resume()
                asyncio.run(_publish_when_subscribed(fleet, address, 0xA1, b"\x07"))
                code, out = alice.finish(30)
                assert code == 0 and json.loads(out)["data"] == "07", alice.stderr_lines
                stats = asyncio.run(query_status(address, tls=tls(fleet, "bob")))["stats"]
                assert stats["impostors"] == 1 and stats["identity_bindings"] >= 1, stats
        finally:
            alice.resume()


async def _publish_when_subscribed(fleet: Path, address: str, node_id: int, data: bytes) -> None:
    """bob publishes ``data`` on robot/speed once the ECB lists ``node_id`` as subscribed."""
    speed = f"0x{name_to_uid('robot/speed'):016x}"
    async with Node(broker=address, node_id=0xB0, tls=tls(fleet, "bob")) as bob:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 20
        while True:
            info = await query_status(address, tls=tls(fleet, "bob"))
            nodes = {n["node_id"]: n for n in info["nodes"]}
            if speed in nodes.get(f"0x{node_id:016x}", {}).get("subscribed", ()):
                break
            assert loop.time() < deadline, f"node {node_id:x} did not come back: {nodes}"
            await asyncio.sleep(0.05)
        await bob.publish("robot/speed", data, wait=True)


async def test_the_bindings_are_written_whole_and_read_back(fleet: Path, tmp_path: Path) -> None:
    ids = tmp_path / "state" / "identities.json"
    async with acl_ecb(fleet, identities=ids) as ecb:
        async with node(fleet, ecb, "alice", 0xA1):
            pass
        await eventually(lambda: ids.exists())
    doc = json.loads(ids.read_text())
    assert doc == {"format": "ups-tcp-ecb-identities", "version": 1,
                   "bindings": [["0x00000000000000a1", "alice"]]}  # fmt: skip
    assert sorted(p.name for p in ids.parent.iterdir()) == [ids.name, f"{ids.name}.lock"]
    async with acl_ecb(fleet, identities=ids) as ecb:  # restarted: 0xa1 is still alice's
        with pytest.raises(AccessDenied, match="is taken"):
            await _squat(fleet, f"127.0.0.1:{ecb.port}", 0xA1)
        with pytest.raises(ConfigError, match="in use by another TCP-ECB"):
            TcpEcb("127.0.0.1", 0, tls=tls(fleet, "broker"), identities=ids)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("{", "Expecting property name"),
        ('{"format": "other", "version": 1, "bindings": []}', "not a file of node id bindings"),
        ('{"format": "ups-tcp-ecb-identities", "version": 2, "bindings": []}', "version 2"),
        ('{"format": "ups-tcp-ecb-identities", "version": 1, "bindings": [["a1", "x"]]}',
         "not a node id and an identity"),
        ('{"format": "ups-tcp-ecb-identities", "version": 1, "bindings": '
         '[["0xa1", "x"], ["0xA1", "y"]]}', "bound twice"),
    ],
)  # fmt: skip
def test_a_bindings_file_that_cannot_be_read_is_a_clear_error_at_start(
    fleet: Path, tmp_path: Path, text: str, why: str
) -> None:
    ids = tmp_path / "identities.json"
    ids.write_text(text)
    with pytest.raises(ConfigError, match=f"cannot use the node id bindings in .*{why}"):
        TcpEcb("127.0.0.1", 0, tls=tls(fleet, "broker"), identities=ids)
    broker = Proc("broker", "--listen", "127.0.0.1:0", "--identities", str(ids),
                  *opts(fleet, "broker"))  # fmt: skip
    code, _ = broker.finish()
    assert code == 2 and "Move the file away to start afresh" in "".join(broker.stderr_lines)


async def test_an_identity_that_makes_up_node_ids_forgets_its_own_not_others(
    fleet: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At most MAX_OWNERS bindings: mallory saying Hello with ever new ids (and leaving) makes
    the ECB forget her own oldest, never alice's."""
    monkeypatch.setattr(_identities, "MAX_OWNERS", 4)
    async with acl_ecb(fleet, identities=tmp_path / "identities.json") as ecb:
        address = f"127.0.0.1:{ecb.port}"
        async with node(fleet, ecb, "alice", 0xA1):
            pass
        for n in range(8):
            async with node(fleet, ecb, "mallory", 0x3A00 + n):
                pass
        await eventually(lambda: ecb.stats()["nodes"] == 0)
        assert ecb.stats()["identity_bindings"] == 4
        with pytest.raises(AccessDenied, match="node id 00000000000000a1 is taken"):
            await _squat(fleet, address, 0xA1)


# --- a node's status ---------------------------------------------------------------------


async def test_a_nodes_port_answers_status_only_to_identities_with_the_right(
    fleet: Path,
) -> None:
    async with acl_ecb(fleet) as ecb, node(fleet, ecb, "alice", 0xA1) as alice:
        await alice.subscribe("robot/speed")
        host, port = alice.face.address  # type: ignore[attr-defined]
        for who in ("mallory", "alice"):  # a fleet identity, alice herself: not in the ACL's
            with pytest.raises(AccessDenied, match=f"identity '{who}' may not read this node"):
                await query_status(f"{host}:{port}", tls=tls(fleet, who))
        mine = await query_status(f"{host}:{port}", tls=tls(fleet, "bob"))  # status = true
        assert mine["node_id"] == "0x00000000000000a1" and mine["stats"]["status_denied"] == 2


async def test_a_subscriber_cannot_ask_its_publisher_for_its_status(fleet: Path) -> None:
    """mallory may subscribe robot/speed: alice, publishing it, dials her. On that link mallory
    asks alice for her Status, and is refused."""
    speed = name_to_uid("robot/speed")
    answers: asyncio.Queue[w.Frame] = asyncio.Queue()

    async def subscriber(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(w.encode(w.StatusRequest()))
        decoder = w.Decoder(max_frame=w.MAX_BODY)
        while data := await reader.read(1 << 16):
            for frame in decoder.feed(data):
                if isinstance(frame, w.Status | w.Refused):
                    await answers.put(frame)
        writer.close()

    context = tls(fleet, "mallory").server()
    server = await asyncio.start_server(subscriber, "127.0.0.1", 0, ssl=context)
    mallory_port = server.sockets[0].getsockname()[1]
    async with server, acl_ecb(fleet) as ecb, node(fleet, ecb, "alice", 0xA1) as alice:
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", ecb.port, ssl=tls(fleet, "mallory").client()
        )
        writer.write(w.encode(w.Hello(0x3A, "mallory", "127.0.0.1", mallory_port)))
        writer.write(w.encode(w.Subscribe(speed, "robot/speed")))
        await eventually(lambda: len(ecb._subscribers.get(speed, ())) == 1)
        await alice.publish("robot/speed", b"\x01")  # alice learns of mallory, and dials her
        answer = await asyncio.wait_for(answers.get(), 10)
        assert isinstance(answer, w.Refused) and answer.right == "status", answer
        assert alice.stats()["status_denied"] == 1
        writer.close()
        del reader


async def test_without_an_acl_every_fleet_identity_may_read_a_nodes_status(fleet: Path) -> None:
    ecb = TcpEcb("127.0.0.1", 0, recovery=0, tls=tls(fleet, "broker"))
    await ecb.start()
    try:
        async with Node(broker=f"127.0.0.1:{ecb.port}", node_id=0xA1,
                        tls=tls(fleet, "alice")) as alice:  # fmt: skip
            host, port = alice.face.address  # type: ignore[attr-defined]
            mine = await query_status(f"{host}:{port}", tls=tls(fleet, "mallory"))
            assert mine["stats"]["status_denied"] == 0
    finally:
        await ecb.close()


# --- receive buffers ------------------------------------------------------------------------


async def test_a_link_not_vouched_for_reads_no_frame_larger_than_its_own_buffer(
    fleet: Path,
) -> None:
    """A fleet identity the ECB vouches for on no channel (mallory) sends a 1 MiB event: its
    body stays unread (nothing is taken from the receive budget) until the doorman closes the
    link. bob's early link, with a 1 MiB event before the ECB's word, waits the same way and
    is read as soon as the ECB vouches for bob: his events come, in order."""
    speed = name_to_uid("robot/speed")
    big = [bytes([n]) * w.MAX_DATA for n in (1, 2)]
    async with (
        acl_ecb(fleet) as ecb,
        node(fleet, ecb, "alice", 0xA1) as alice,
        node(fleet, ecb, "bob", 0xB0) as bob,
    ):
        sub = await alice.subscribe("robot/speed")
        inbox = alice.face._inbox  # type: ignore[attr-defined]
        inbox._doorman.hello_timeout = 2.0
        links = []
        for who, node_id in (("mallory", 0x3A), ("bob", 0xB0)):
            reader, writer = await asyncio.open_connection(
                *alice.face.address,  # type: ignore[attr-defined]
                ssl=tls(fleet, who).client(),
            )
            writer.write(w.encode(w.Hello(node_id, who, "127.0.0.1", 1)))
            writer.write(w.encode(w.Start(speed, 1)) + w.encode_event(speed, big[0], 0, 1))
            links.append((reader, writer))
        await eventually(lambda: sum(link.partial() for link in inbox._links) == 2)
        assert alice.stats()["receive_held"] == 0  # neither body is read
        await bob.publish("robot/speed", big[1])  # bob advertises: the ECB vouches for him
        assert [(await sub.get_msg(timeout=5)).data for _ in range(2)] == big
        with contextlib.suppress(ConnectionResetError):  # (reset: it had data left unread)
            assert await asyncio.wait_for(links[0][0].read(), 10) == b""  # mallory's: timed out
        assert inbox._doorman.counters["timed_out"] == 1 and alice.stats()["unvouched"] == 0
        for _, writer in links:
            writer.close()
