"""Access control at the TCP-ECB: a valid certificate is not enough, the ACL says who may do what.

Real sockets on loopback over TLS, certificates made by ``ups certs``; the gateway test runs a
virtual CAN bus. What must never happen: an event delivered to an identity that may not
subscribe it, an event accepted from an identity that may not publish it, a refusal that does
not name the channel and the right.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
from collections.abc import AsyncIterator
from pathlib import Path

import can
import pytest

from ups import AccessDenied, BrokerUnavailable, Channel, ConfigError, Node, _tcpinbox, name_to_uid
from ups import _tcpwire as w
from ups._tcpface import query_status
from ups.broker._acl import Acl
from ups.broker.tcp_ecb import TcpEcb
from ups.gateway import Gateway

from .conftest import eventually
from .procs import Proc
from .test_tls import certs, tls

ACL = """
[identity.alice]                      # a robot: its own channels, and the fleet's commands
publish = ["robot/*", "0x00000000000000a1"]
subscribe = ["robot/*", "fleet/go"]

[identity.bob]                        # the operator station
publish = ["fleet/*", "robot/speed"]
subscribe = ["*"]
status = true
node_ids = ["0xb0"]                   # its node id: no other identity may say Hello with it

[identity.mallory]                    # a valid certificate with almost no rights
subscribe = ["robot/speed"]

[identity.gw]                         # a gateway: only what its CAN bus may see
subscribe = ["robot/speed"]
publish = ["robot/*"]
"""


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("acl-fleet")
    certs(folder, "ca", str(folder))
    for name in ("broker", "alice", "bob", "mallory", "gw", "eve"):
        certs(folder, "issue", str(folder), name)
    (folder / "acl.toml").write_text(ACL)
    return folder


@contextlib.asynccontextmanager
async def acl_ecb(fleet: Path, identities: Path | None = None) -> AsyncIterator[TcpEcb]:
    ecb = TcpEcb("127.0.0.1", 0, recovery=0, tls=tls(fleet, "broker"),
                 acl=Acl.load(fleet / "acl.toml"), identities=identities)  # fmt: skip
    await ecb.start()
    try:
        yield ecb
    finally:
        await ecb.close()


def node(fleet: Path, ecb: TcpEcb, who: str, node_id: int) -> Node:
    return Node(broker=f"127.0.0.1:{ecb.port}", node_id=node_id, name=who, join_timeout=5,
                tls=tls(fleet, who))  # fmt: skip


# --- the file ------------------------------------------------------------------------------


def test_entries_are_names_globs_and_uids() -> None:
    acl = Acl.parse(ACL)
    speed = name_to_uid("robot/speed")
    assert acl.allows("alice", "publish", speed, "robot/speed")
    assert not acl.allows("alice", "publish", speed, None)  # a glob needs the name
    assert acl.allows("alice", "publish", 0xA1, None)
    assert acl.allows("mallory", "subscribe", speed, None)  # a literal name matches its UID
    assert not acl.allows("mallory", "publish", speed, "robot/speed")
    assert acl.allows("bob", "subscribe", 0x1234, None)  # "*" is every channel
    assert not acl.allows("eve", "subscribe", speed, "robot/speed")  # not listed: nothing
    assert not acl.allows(None, "subscribe", speed, "robot/speed")
    assert acl.may_status("bob") and not acl.may_status("alice")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[identity.a]\npublish = 'x'", "publish must be a list of strings"),
        ("[identity.a]\nsubscribe = ['0xZZ']", "bad channel UID"),
        ("[identity.a]\npublsh = ['x']", "unknown key 'publsh'"),
        ("[identity.a]\nstatus = 'yes'", "status must be true or false"),
        ("[users.a]\npublish = []", "unknown top-level key 'users'"),
        ("[identity.a\n", "not TOML"),
        ("[identity.a]\npublish = ['']", "entry ''"),
    ],
)
def test_a_bad_acl_is_a_clear_error(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        Acl.parse(text, "acl.toml")


def test_an_acl_needs_tls() -> None:
    with pytest.raises(ConfigError, match="an ACL needs TLS"):
        TcpEcb("127.0.0.1", 0, acl=Acl.parse(ACL))


# --- the broker refuses --------------------------------------------------------------------


async def test_refusals_name_the_channel_and_the_right(fleet: Path) -> None:
    async with acl_ecb(fleet) as ecb, node(fleet, ecb, "alice", 0xA1) as alice:
        with pytest.raises(AccessDenied, match="may not subscribe secret/plans") as info:
            await alice.subscribe("robot/speed", "secret/plans")
        assert (info.value.channel, info.value.right) == ("secret/plans", "subscribe")
        with pytest.raises(AccessDenied, match="may not publish fleet/go"):
            await alice.publish("fleet/go", b"")
        # A name that is not the name of its UID is refused, whatever the ACL says of the name.
        with pytest.raises(AccessDenied, match="'robot/speed' is the name of"):
            await alice.subscribe(Channel(0x5EC, "robot/speed"))
        status = await query_status(f"127.0.0.1:{ecb.port}", tls=tls(fleet, "bob"))
        # The refused subscribe took back robot/speed too: alice is registered for nothing.
        assert list(status["nodes"][0]["subscribed"]) == [] and status["stats"]["denied"] == 3
        assert alice.stats()["denied"] == 3
        with pytest.raises(AccessDenied, match="may not read the broker's tables"):
            await query_status(f"127.0.0.1:{ecb.port}", tls=tls(fleet, "alice"))


async def test_an_identity_not_in_the_acl_cannot_even_join(fleet: Path) -> None:
    async with acl_ecb(fleet) as ecb:
        eve = node(fleet, ecb, "eve", 0xE1)
        with pytest.raises(AccessDenied, match="identity 'eve' is not in the ACL"):
            await eve.start()  # at once, not after the join timeout
        await eve.close()
        assert ecb.stats()["nodes"] == 0 and ecb.stats()["denied"] == 1


async def test_a_valid_client_without_the_right_cannot_inject(
    fleet: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_tcpinbox, "VOUCH_WAIT", 0.5)
    speed = name_to_uid("robot/speed")
    async with (
        acl_ecb(fleet) as ecb,
        node(fleet, ecb, "alice", 0xA1) as alice,
        node(fleet, ecb, "bob", 0xB0) as bob,
    ):
        sub = await alice.subscribe("robot/speed")
        await bob.publish("robot/speed", b"bob-1")
        assert (await sub.get_msg(timeout=5)).data == b"bob-1"
        # mallory writes straight to alice's listening port, even claiming bob's node id
        forged = [w.encode(w.Start(speed, 1))] + [
            w.encode_event(speed, b"forged", 0, n) for n in range(1, 101)
        ]
        assert alice.face.address is not None  # type: ignore[attr-defined]
        hello = w.Hello(0xB0, "bob", "127.0.0.1", 1)
        await _inject_as(fleet, "mallory", alice, hello, forged)
        assert alice.stats()["unvouched"] == 100  # held, refused, counted, link closed
        await bob.publish("robot/speed", b"bob-2")
        assert (await sub.get_msg(timeout=5)).data == b"bob-2"
        assert sub.dropped == 0 and not sub._queue  # nothing forged ever came through
        with pytest.raises(AccessDenied, match="may not publish robot/speed"):
            async with node(fleet, ecb, "mallory", 0x3A) as mallory:
                await mallory.publish("robot/speed", b"forged")


async def test_a_link_that_comes_before_the_brokers_word_waits_for_it(fleet: Path) -> None:
    """bob's events reach alice before the ECB told her that bob publishes: she holds them,
    unread, and delivers them in order once the word comes."""
    speed = name_to_uid("robot/speed")
    async with (
        acl_ecb(fleet) as ecb,
        node(fleet, ecb, "alice", 0xA1) as alice,
        node(fleet, ecb, "bob", 0xB0) as bob,
    ):
        sub = await alice.subscribe("robot/speed")
        early = [w.encode(w.Start(speed, 1))]
        early += [w.encode_event(speed, bytes([n]), 0x40, n) for n in range(1, 6)]
        reader, writer = await asyncio.open_connection(
            *alice.face.address,
            ssl=tls(fleet, "bob").client(),  # type: ignore[attr-defined]
        )
        writer.write(w.encode(w.Hello(0xB0, "bob-early", "127.0.0.1", 1)) + b"".join(early))
        await eventually(lambda: bool(alice.face._inbox._holding))  # type: ignore[attr-defined]
        assert not sub._queue
        await bob.publish("robot/speed", b"late")  # bob advertises: the ECB vouches for bob
        got = [(await sub.get_msg(timeout=5)).data for _ in range(6)]
        assert [d for d in got if d != b"late"] == [bytes([n]) for n in range(1, 6)]
        assert b"late" in got
        assert alice.stats()["unvouched"] == 0 and alice.stats()["lost"] == 0
        writer.close()
        del reader


async def test_events_go_only_to_the_identity_the_broker_listed(fleet: Path) -> None:
    """mallory registers alice's listening address as its own: bob's events for mallory must
    not land at alice (she would get every event twice), and bob counts an impostor."""
    async with (
        acl_ecb(fleet) as ecb,
        node(fleet, ecb, "alice", 0xA1) as alice,
        node(fleet, ecb, "bob", 0xB0) as bob,
    ):
        sub = await alice.subscribe("robot/speed")
        host, port = alice.face.address  # type: ignore[attr-defined]
        context = tls(fleet, "mallory").client()
        reader, writer = await asyncio.open_connection("127.0.0.1", ecb.port, ssl=context)
        writer.write(w.encode(w.Hello(0x3A, "mallory", host, port)))
        writer.write(w.encode(w.Subscribe(name_to_uid("robot/speed"), "robot/speed")))
        await eventually(lambda: len(ecb._subscribers.get(name_to_uid("robot/speed"), ())) == 2)
        for n in range(20):
            await bob.publish("robot/speed", bytes([n]))
        await eventually(lambda: bob.stats()["impostors"] >= 1)
        got = [(await sub.get_msg(timeout=5)).data for _ in range(20)]
        assert got == [bytes([n]) for n in range(20)]
        await bob.publish("robot/speed", b"end")
        assert (await sub.get_msg(timeout=5)).data == b"end"  # no duplicate before it
        writer.close()
        del reader


# --- the gateway ---------------------------------------------------------------------------


async def test_what_the_gateway_may_not_receive_never_reaches_its_bus(
    fleet: Path, bus: str, raw_bus: can.BusABC, tmp_path: Path
) -> None:
    async with (
        acl_ecb(fleet) as ecb,
        Gateway(bus, f"127.0.0.1:{ecb.port}", db=tmp_path / "gw.db", node_id=0x6A7E,
                tls=tls(fleet, "gw"), recovery=0.1) as gw,
        Node(can=bus, node_id=0xC1) as can_node,
        node(fleet, ecb, "bob", 0xB0) as bob,
    ):  # fmt: skip
        secret, speed = (
            await can_node.subscribe("fleet/secret"),
            await can_node.subscribe("robot/speed"),
        )
        await eventually(lambda: gw.stats()["denied"] >= 1)  # fleet/secret: not for gw
        await eventually(lambda: name_to_uid("robot/speed") in gw._to_can_sinks)
        await bob.publish("fleet/secret", b"\x01")
        await bob.publish("robot/speed", b"\x02")
        await eventually(lambda: bob.stats()["sent"] >= 1)
        assert (await speed.get_msg(timeout=5)).data == b"\x02"
        assert not secret._queue and gw.stats()["to_can"] == 1
        status = await query_status(f"127.0.0.1:{ecb.port}", tls=tls(fleet, "bob"))
        secret_uid = f"0x{name_to_uid('fleet/secret'):016x}"
        assert all(secret_uid not in n["subscribed"] for n in status["nodes"])
        frames = []
        while (frame := raw_bus.recv(0)) is not None:
            frames.append(frame)
        assert not any(f.data == b"\x01" for f in frames)  # the secret never reached the bus


# --- invariants under random use -----------------------------------------------------------


@pytest.mark.parametrize("seed", range(3))
async def test_random_use_never_delivers_what_the_acl_forbids(fleet: Path, seed: int) -> None:
    """Random subscribes and publishes by three identities: every call is refused exactly when
    the ACL says so, and every delivery is one the ACL allows both ends."""
    rng = random.Random(seed)
    acl = Acl.parse(ACL)
    names = ["robot/speed", "robot/arm", "fleet/go", "fleet/stop", "misc"]
    who = ["alice", "bob", "mallory"]
    async with acl_ecb(fleet) as ecb, contextlib.AsyncExitStack() as stack:
        nodes = {n: await stack.enter_async_context(node(fleet, ecb, n, 0x100 + i))
                 for i, n in enumerate(who)}  # fmt: skip
        for n in ("alice", "mallory"):
            await nodes[n].subscribe("robot/speed")
        sent: list[tuple[str, str, bytes]] = []
        for step in range(40):
            actor, channel = rng.choice(who), rng.choice(names)
            uid = name_to_uid(channel)
            if rng.random() < 0.3:
                allowed = acl.allows(actor, "subscribe", uid, channel)
                try:
                    await nodes[actor].subscribe(channel)
                    assert allowed, f"{actor} subscribed to {channel}"
                except AccessDenied as exc:
                    assert not allowed and exc.right == "subscribe"
            else:
                allowed = acl.allows(actor, "publish", uid, channel)
                data = f"{step}".encode()
                try:
                    await nodes[actor].publish(channel, data, wait=True)
                    assert allowed, f"{actor} published on {channel}"
                    sent.append((actor, channel, data))
                except AccessDenied as exc:
                    assert not allowed and exc.right == "publish"
        ends = {b"end-alice", b"end-bob"}  # each publisher's last event: FIFO per link
        await nodes["alice"].publish("robot/speed", b"end-alice")
        await nodes["bob"].publish("robot/speed", b"end-bob")
        sent += [("alice", "robot/speed", b"end-alice"), ("bob", "robot/speed", b"end-bob")]
        for n in ("alice", "mallory"):
            waiting = set(ends) - ({b"end-alice"} if n == "alice" else set())
            while waiting:
                msg = await nodes[n].get_msg(timeout=5)
                waiting.discard(msg.data)
                allowed_sub = acl.allows(n, "subscribe", msg.uid, msg.channel.name)
                assert allowed_sub, f"{n} got {msg.channel}"
                if msg.source is not None:  # from another node: it had the right to publish
                    senders = {a for a, c, d in sent if c == msg.channel.name and d == msg.data}
                    assert senders and all(
                        acl.allows(a, "publish", msg.uid, msg.channel.name) for a in senders
                    )
        for n in who:
            assert nodes[n].stats()["unvouched"] == 0


def test_the_command_line_names_what_is_refused(fleet: Path) -> None:
    def opts(name: str) -> list[str]:
        return ["--tls-ca", str(fleet / "ca.crt"), "--tls-cert", str(fleet / f"{name}.crt"),
                "--tls-key", str(fleet / f"{name}.key")]  # fmt: skip

    with Proc("broker", "--listen", "127.0.0.1:0", "--recovery", "0",
              "--acl", str(fleet / "acl.toml"), *opts("broker")) as broker:  # fmt: skip
        line = broker.wait_for_line(r"TCP-ECB on 127\.0\.0\.1:\d+")
        address = line.split("TCP-ECB on ")[1].split()[0]
        cases = [
            (["sub", "secret/plans", *opts("alice")], "may not subscribe secret/plans"),
            (["pub", "fleet/go", "01", *opts("alice")], "may not publish fleet/go"),
            (["sub", "robot/speed", *opts("eve")], "identity 'eve' is not in the ACL"),
        ]
        for args, message in cases:
            proc = Proc(*args, "--broker", address, "--join-timeout", "10")
            try:
                code, _ = proc.finish()
            except AssertionError:
                raise AssertionError(f"{args[:2]}: {proc.stderr_lines[-3:]}") from None
            assert code == 2 and message in "".join(proc.stderr_lines), proc.stderr_lines
        status = Proc("status", address, *opts("alice"))
        assert status.finish()[0] == 2 and "status" in "".join(status.stderr_lines)
        status = Proc("status", address, *opts("bob"))
        assert status.finish()[0] == 0
    plain = Proc("broker", "--listen", "127.0.0.1:0", "--acl", str(fleet / "acl.toml"))
    assert plain.finish()[0] == 2 and "an ACL needs TLS" in "".join(plain.stderr_lines)
    missing = Proc("broker", "--acl", str(fleet / "nope.toml"), *opts("broker"))
    assert missing.finish()[0] == 2 and "cannot read the ACL" in "".join(missing.stderr_lines)


# --- what a holder of a fleet certificate tried (the review's findings, kept as tests) -------


async def test_a_node_joins_only_the_fleet_broker(fleet: Path) -> None:
    """mallory runs a TCP-ECB of her own with her certificate: nodes will not join it."""
    fake = TcpEcb("127.0.0.1", 0, recovery=0, tls=tls(fleet, "mallory"))
    await fake.start()
    try:
        alice = Node(broker=f"127.0.0.1:{fake.port}", node_id=0xA1, join_timeout=1,
                     tls=tls(fleet, "alice"))  # fmt: skip
        with pytest.raises(BrokerUnavailable, match="shows identity 'mallory'"):
            await alice.start()
        await alice.close()
        assert fake.stats()["nodes"] == 0
    finally:
        await fake.close()


async def test_links_nobody_vouched_for_make_room_for_a_publisher(
    fleet: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """eve (no rights at all) fills alice's publisher slots with links that said Hello: bob's
    link still gets in, and eve's are the ones closed."""
    monkeypatch.setattr(_tcpinbox, "MAX_PUBLISHERS", 8)
    async with (
        acl_ecb(fleet) as ecb,
        node(fleet, ecb, "alice", 0xA1) as alice,
        node(fleet, ecb, "bob", 0xB0) as bob,
    ):
        sub = await alice.subscribe("robot/speed")
        writers = []
        for n in range(8):
            _, writer = await asyncio.open_connection(
                *alice.face.address,
                ssl=tls(fleet, "eve").client(),  # type: ignore[attr-defined]
            )
            writer.write(w.encode(w.Hello(0xE0 + n, "eve", "127.0.0.1", 1)))
            writers.append(writer)
        inbox = alice.face._inbox  # type: ignore[attr-defined]
        await eventually(lambda: len(inbox._waiting) == 8)
        await bob.publish("robot/speed", b"through")
        assert (await sub.get_msg(timeout=5)).data == b"through"
        assert inbox._doorman.counters["evicted"] >= 1
        for writer in writers:
            writer.close()


async def test_a_client_that_never_reads_refusals_is_cut_off(fleet: Path) -> None:
    """Registrations with long bogus names, answers never read: each answer stays short, and
    the ECB cuts the link off at its control-queue bound instead of growing."""
    async with acl_ecb(fleet) as ecb:
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", ecb.port, ssl=tls(fleet, "mallory").client()
        )
        writer.write(w.encode(w.Hello(0x3A, "mallory", "127.0.0.1", 1)))
        bogus = w.encode(w.Subscribe(1, "x" * 200 + "/not-the-name-of-1"))
        for _ in range(20):
            writer.write(bogus * 1000)
        await eventually(lambda: ecb.stats()["denied"] >= 16384, timeout=20)
        await eventually(lambda: ecb.stats()["nodes"] == 0, timeout=10)  # link cut: it leaves
        writer.close()
        del reader
        async with node(fleet, ecb, "alice", 0xA1) as alice:  # and the ECB serves on
            await alice.subscribe("robot/speed")


async def test_frames_after_a_bad_one_are_ignored_not_crashed_on(
    fleet: Path, caplog: pytest.LogCaptureFixture
) -> None:
    async with acl_ecb(fleet) as ecb:
        speed = name_to_uid("robot/speed")
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", ecb.port, ssl=tls(fleet, "mallory").client()
        )
        writer.write(w.encode(w.Hello(0x3A, "mallory", "127.0.0.1", 1)))
        writer.write(w.encode(w.Subscribe(speed, "robot/speed")))
        await eventually(lambda: speed in ecb._subscribers)
        burst = w.encode_event(speed, b"", 0, 1) + w.encode(w.Subscribe(speed, "robot/speed"))
        writer.write(w.encode(w.Subscribe(speed, "robot/speed")) + burst)
        await reader.read()  # until the ECB closes the link
        writer.close()
        async with node(fleet, ecb, "bob", 0xB0) as bob:
            await bob.publish("robot/speed", b"")
        assert not [r for r in caplog.records if r.levelname == "ERROR"]


async def test_forged_starts_and_node_ids_change_nothing(fleet: Path) -> None:
    """alice may publish robot/speed, but not as bob: a link claiming bob's node id with her
    certificate is refused; Starts from it neither fake losses nor grow any table."""
    speed = name_to_uid("robot/speed")
    async with (
        acl_ecb(fleet) as ecb,
        node(fleet, ecb, "alice", 0xA1) as alice,
        node(fleet, ecb, "bob", 0xB0) as bob,
        node(fleet, ecb, "mallory", 0x3A) as mallory,
    ):
        sub = await mallory.subscribe("robot/speed")
        await bob.publish("robot/speed", b"bob-1")
        await alice.publish("robot/speed", b"alice-1")
        got = {(m.data, m.source) for m in [await sub.get_msg(timeout=5) for _ in range(2)]}
        assert got == {(b"bob-1", 0xB0), (b"alice-1", 0xA1)}
        inbox = mallory.face._inbox  # type: ignore[attr-defined]
        tables = len(inbox._expected)
        frames = [w.encode(w.Start(speed, (1 << 64) - 2))]
        frames += [w.encode(w.Start(uid, 5)) for uid in range(1000, 2000)]
        frames += [w.encode_event(speed, b"not bob", 0, (1 << 64) - 2)]
        await _inject_as(fleet, "alice", mallory, w.Hello(0xB0, "bob", "127.0.0.1", 1), frames)
        assert len(inbox._expected) == tables and mallory.stats()["lost"] == 0
        assert mallory.stats()["unvouched"] == 1
        await bob.publish("robot/speed", b"bob-2")
        assert (await sub.get_msg(timeout=5)).data == b"bob-2"
        assert mallory.stats()["lost"] == 0 and not sub._queue


async def _inject_as(
    fleet: Path, who: str, target: Node, hello: w.Hello, frames: list[bytes]
) -> None:
    """Connect to ``target``'s listening port with ``who``'s certificate, write ``hello`` and
    ``frames``, and wait until the target closes the link."""
    reader, writer = await asyncio.open_connection(
        *target.face.address,
        ssl=tls(fleet, who).client(),  # type: ignore[attr-defined]
    )
    writer.write(w.encode(hello) + b"".join(frames))
    await writer.drain()
    await reader.read()  # until the target closes the link
    writer.close()
