"""The TCP-ECB: the registry of a TCP/IP network's nodes and of who subscribes to what.

Nodes connect, say Hello (node id, name, the address they listen on), then register the
channels they subscribe to and publish on. The ECB answers every Subscribe and Advertise with
the channel's current subscriber list, and pushes the new list to the channel's publishers
whenever it changes. It is never on the data path: publishers connect to subscribers directly.

Liveness: every frame from a node counts as a sign of life (nodes Ping every 0.5 s). A node
silent for ``liveness`` seconds, or whose link ended and did not come back within that time,
leaves every list. A node that closed its link after withdrawing everything leaves at once.

Access control (with TLS): a node's identity is its certificate's common name; with an ACL
(``broker/_acl.py``) the ECB refuses, with a ``Refused`` frame, what the identity may not do.
It tells each subscriber which identities publish on its channels (``Publishers``), so the
subscriber accepts events only from those, and each publisher the identity of each subscriber
(in ``Subscribers``), so it sends events only to those.

Recovery: an ECB that just started knows nothing, and nodes reconnect with backoff. For its
first ``recovery`` seconds it collects registrations and answers none, so no publisher is told
a half-rebuilt list (which would cut events to subscribers that have not re-registered yet).

Its own work never makes it drop a node: a Status costs what it lists, at most once per
``STATUS_GAP`` (``ups._statuspacer``); silence counts only while it reads (``_liveness``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from pathlib import Path
from typing import Any

from ups import _tcpwire as w
from ups._address import DEFAULT_PORT, parse_address
from ups._errors import ConfigError
from ups._statuspacer import StatusPacer
from ups._tcpface import HEARTBEAT
from ups._tcplink import Doorman, Link, link_budget
from ups._tls import Tls, identity

from ._acl import Acl
from ._identities import Identities
from ._liveness import sweep
from ._tcpmember import Member
from ._tcprights import refusal
from ._tcpstatus import registry_status
from ._watches import Watches

log = logging.getLogger("ups.tcp_ecb")

DEFAULT_LIVENESS = 3.0
DEFAULT_RECOVERY = 1.5  # > the nodes' longest reconnect backoff (1 s)
_LINK_LIMIT = 1 << 16  # frames queued to a node that does not read: then it is cut off
MAX_CHANNELS = 8192  #: channels one node may register (subscribe to and publish on)
_REGISTERED_FRAME = 1 << 16  #: the longest frame a registered node sends the TCP-ECB


class TcpEcb:
    """A TCP-ECB listening on ``host:port`` (port 0: any free port; see ``port`` once started)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        *,
        liveness: float = DEFAULT_LIVENESS,
        recovery: float = DEFAULT_RECOVERY,
        max_links: int | None = None,
        hello_timeout: float = 5.0,
        tls: Tls | None = None,
        acl: Acl | None = None,
        identities: Path | None = None,
    ) -> None:
        """``identities``: the file that keeps the node id <-> identity bindings (with TLS) across
        restarts (``broker/_identities.py``; None: they last as long as the ECB runs)."""
        if acl is not None and tls is None:
            raise ConfigError(
                "an ACL needs TLS (identities are certificate names): give --tls-ca, --tls-cert "
                "and --tls-key too"
            )
        if liveness < 2 * HEARTBEAT:
            raise ConfigError(
                f"liveness must be at least {2 * HEARTBEAT:g} s (nodes ping every {HEARTBEAT:g} s)"
            )
        self.host = host
        self.port = port
        self.liveness = liveness
        self.recovery = recovery
        self._server: asyncio.AbstractServer | None = None
        self._members: dict[int, Member] = {}
        self._subscribers: dict[int, set[int]] = {}  # uid -> node ids
        self._publishers: dict[int, set[int]] = {}  # uid -> node ids
        self._channel_count = 0  # UIDs in _subscribers or _publishers (or both)
        self._links: set[Link] = set()
        self._recovering = False
        self._waiting: dict[tuple[int, bool], set[int]] = {}  # owed after recovery:
        # (uid, subscribe) -> node ids
        self._tasks: list[asyncio.Task[None]] = []
        self._tls = tls
        self._acl = acl
        self._names: dict[int, str] = {}  # uid -> its name, checked against the UID
        self._watches = Watches(self._names, self._members, acl, self._push)
        self._refusals_logged: set[tuple[str | None, str, int]] = set()
        self._doorman = Doorman(
            link_budget() if max_links is None else max_links, hello_timeout=hello_timeout
        )
        self.counters = dict.fromkeys(
            ("joined", "left", "malformed", "pushes", "limited", "impostors", "denied", "errors",
             "held_up"), 0,
        )  # fmt: skip
        self._pacer = StatusPacer(self.status, self.counters, who="the TCP-ECB")
        #: node id -> identity (TLS): the ACL's pins, the bindings made (kept in a file)
        self._owners = Identities(acl.pins() if acl else {}, identities if tls else None,
                                  self.counters)  # fmt: skip
        #: told each node after its Hello (TLS): who may read its Status (the ACL's right)
        readers = w.StatusReaders(acl.status_readers() if acl else None)
        self._readers = w.encode(readers) if tls else None

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            lambda: self._new_link().protocol,
            self.host,
            self.port,
            reuse_address=True,
            ssl=self._tls.server() if self._tls else None,
        )
        self.port = self._server.sockets[0].getsockname()[1]
        self._recovering = self.recovery > 0
        if self._recovering:
            self._tasks.append(loop.create_task(self._end_recovery()))
        self._tasks.append(
            loop.create_task(sweep(self._members, self.liveness, self._leave, self.counters))
        )
        log.info(
            "TCP-ECB on %s:%d (liveness %g s, recovery %g s%s%s)",
            self.host,
            self.port,
            self.liveness,
            self.recovery,
            ", TLS" if self._tls else "",
            f", ACL {self._acl.source}: {len(self._acl)} identities" if self._acl else "",
        )

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks.clear()
        if self._server is not None:
            self._server.close()
            self._server = None
        for link in list(self._links):
            link.close()
        self._doorman.close()
        self._pacer.close()
        await self._owners.close()

    def stats(self) -> dict[str, int]:
        return {
            **self.counters,
            **self._doorman.counters,
            **self._watches.counters,
            "nodes": len(self._members),
            "watches": len(self._watches),
            "channels": self._channel_count,
            "links": self._doorman.links,
        }

    def status(self) -> dict[str, Any]:
        """The registry, as ``ups status`` prints it (bounded: see ``_tcpstatus``)."""
        return registry_status(
            self._members, self._subscribers, self._publishers, self._names, self.stats()
        )

    # --- links -----------------------------------------------------------------------------

    def _new_link(self) -> Link:
        link = Link(
            self._on_event, self._on_frame, self._on_lost, limit=_LINK_LIMIT,
            max_frame=_REGISTERED_FRAME,
        )  # fmt: skip
        self._links.add(link)
        self._doorman.admit(link)
        return link

    def _on_event(self, link: Link, uid: int, data: bytes, priority: int, seq: int) -> None:
        if link.lost.done():  # the rest of a read after we closed the link
            return
        self.counters["malformed"] += 1
        log.warning("closed the link from %s: events do not go through the ECB", link.name)
        link.abort("sent an event to the ECB")

    def _on_frame(self, link: Link, frame: w.Frame) -> None:
        if link.lost.done():  # the rest of a read after we closed the link: ignored
            return
        member: Member | None = link.peer
        if isinstance(frame, w.StatusRequest):
            if self._acl is None or self._acl.may_status(identity(link.transport)):
                self._doorman.asked(link)  # evicted last while it waits for its answer
                self._pacer.ask(link)  # answered with the next Status, built at most so often
            else:
                self._refuse(link, 0, "status", "its identity may not read the broker's tables")
            return
        if member is None:
            if isinstance(frame, w.Hello):
                name = identity(link.transport)
                if self._acl is not None and name not in self._acl:
                    self._refuse(link, 0, "connect", f"identity {name!r} is not in the ACL")
                    link.close()
                    return
                if not self._owned_by(link, frame.node_id):
                    return
                self._doorman.greeted(link)
                self._hello(link, frame)
            else:
                self.counters["malformed"] += 1
                log.warning("closed the link from %s: %s before Hello", link.name, frame)
                link.abort("no Hello")
            return
        member.heard = time.monotonic()
        if isinstance(frame, w.Subscribe | w.Unsubscribe | w.Advertise | w.Unadvertise):
            self._register(member, frame)
        elif isinstance(frame, w.Watch | w.Unwatch):  # see _watches
            if (why := self._watches.handle(member.node_id, frame)) is not None:
                self._refuse(link, 0, "watch", why)
        elif isinstance(frame, w.Ping):
            if member.stale is not None:
                self._forget_stale(member)
                self._watches.renewed(member.node_id)
            link.send_control(w.encode(w.Pong()))
        elif not isinstance(frame, w.Pong):
            self.counters["malformed"] += 1
            log.warning("closed the link from %s: unexpected %s", link.name, frame)
            link.abort("unexpected frame")

    def _owned_by(self, link: Link, node_id: int) -> bool:
        """With TLS, a node id belongs to the identity the ACL pins it to, or else to the one
        that first registered it, also after the node left and across restarts (no takeover,
        no squatting while it restarts: ``_identities``): another identity saying Hello with
        it is refused."""
        name = identity(link.transport)
        if name is None:
            return True
        owner = self._owners.claim(node_id, name, self._members)
        if owner is None:
            return True
        self.counters["impostors"] += 1
        log.warning("refused %s: node id %016x belongs to %s", name, node_id, owner)
        link.send_control(w.encode(w.Refused(0, "connect", f"node id {node_id:016x} is taken "
                                             "by another identity")))  # fmt: skip
        link.close()
        return False

    def _refuse(self, link: Link, uid: int, right: str, reason: str) -> None:
        """Tell the node what it may not do, count it, and log it once per kind of refusal."""
        self.counters["denied"] += 1
        link.send_control(w.encode(w.Refused(uid, right, reason)))
        who = identity(link.transport)
        key = (who, right, uid)
        if key not in self._refusals_logged and len(self._refusals_logged) < 4096:
            self._refusals_logged.add(key)
            log.warning("refused %s %s on %016x: %s", who or link.name, right, uid, reason)

    def _on_lost(self, link: Link, reason: str | None) -> None:
        self._links.discard(link)
        self._doorman.gone(link)
        if reason is not None and reason.startswith("bad frame"):
            self.counters["malformed"] += 1
        member: Member | None = link.peer
        if member is None or member.link is not link:
            return
        member.link = None
        if not member.subs and not member.pubs and not self._watches.watches(member.node_id):
            self._leave(member, "closed its link")
        else:
            log.info(
                "node %016x (%s) lost its link (%s); it leaves in %g s unless it comes back",
                member.node_id,
                member.name,
                reason or "closed",
                self.liveness,
            )

    # --- the registry ----------------------------------------------------------------------

    def _hello(self, link: Link, hello: w.Hello) -> None:
        member = self._members.get(hello.node_id)
        if member is None:
            member = self._members[hello.node_id] = Member(hello, link)
            self.counters["joined"] += 1
            log.info(
                "node %016x (%s) joined from %s:%d",
                hello.node_id,
                hello.name,
                hello.host,
                hello.port,
            )
        else:  # the same node again: after a lost link, or restarted
            self._watches.renewing(hello.node_id)  # it watches again what it still watches
            old = member.link
            member.link = link
            member.name = hello.name
            member.heard = time.monotonic()
            if old is not None:
                old.abort("replaced by a new link of the same node")
            # What it does not register again before its first Ping, it no longer has.
            member.stale = {(True, uid) for uid in member.subs} | {
                (False, uid) for uid in member.pubs
            }
            if member.address != (hello.host, hello.port):
                member.address = (hello.host, hello.port)
                for uid in member.subs | self._watches.implied_of(hello.node_id):
                    self._push(uid)
            log.info(
                "node %016x (%s) is back from %s:%d", hello.node_id, hello.name, *member.address
            )
        link.peer = member
        link.send_control(w.encode(w.Hello(0, "ups-broker", self.host, self.port)))
        if self._readers is not None:
            link.send_control(self._readers)

    def _register(
        self, member: Member, frame: w.Subscribe | w.Unsubscribe | w.Advertise | w.Unadvertise
    ) -> None:
        uid = frame.uid
        subscribe = isinstance(frame, w.Subscribe | w.Unsubscribe)
        adding = isinstance(frame, w.Subscribe | w.Advertise)
        mine = member.subs if subscribe else member.pubs
        table = self._subscribers if subscribe else self._publishers
        if member.stale is not None:
            member.stale.discard((subscribe, uid))
        if adding:
            assert isinstance(frame, w.Subscribe | w.Advertise)
            new = uid not in mine
            if not self._admitted(member, frame, subscribe, new):
                return
            mine.add(uid)
            if uid not in self._subscribers and uid not in self._publishers:
                self._channel_count += 1
            table.setdefault(uid, set()).add(member.node_id)
            if frame.name is not None and self._names.get(uid) != frame.name:
                self._names[uid] = frame.name
                self._watches.named(uid, frame.name)
            if subscribe:  # publishers hear of a new subscriber before it is answered
                if new:
                    self._push(uid, skip=member.node_id)
                self._answer(member, uid, subscribe=True)
            else:  # subscribers hear of a new publisher before it hears of them
                if new:
                    self._vouch(uid, member)
                self._answer(member, uid, subscribe=False)
        elif uid in mine:
            mine.discard(uid)
            self._discard(table, uid, member.node_id)
            if subscribe:
                self._push(uid)
            else:
                self._vouch(uid, member)

    def _admitted(
        self, member: Member, frame: w.Subscribe | w.Advertise, sub: bool, new: bool
    ) -> bool:
        """Whether the node may make (or renew) this registration; if not, it is told why."""
        uid, right = frame.uid, "subscribe" if sub else "publish"
        assert member.link is not None
        if new and len(member.subs) + len(member.pubs) >= MAX_CHANNELS:
            self.counters["limited"] += 1
            self._refuse(member.link, uid, right,
                         f"a node may register at most {MAX_CHANNELS} channels")  # fmt: skip
            return False
        why = refusal(member.identity, frame, right, self._names, self._acl)
        if why is not None:
            self._refuse(member.link, uid, right, why)
        return why is None

    def _forget_stale(self, member: Member) -> None:
        stale, member.stale = member.stale or set(), None
        for subscribe, uid in stale:
            frame = w.Unsubscribe(uid) if subscribe else w.Unadvertise(uid)
            self._register(member, frame)

    def _leave(self, member: Member, why: str) -> None:
        del self._members[member.node_id]
        self.counters["left"] += 1
        log.info("node %016x (%s) left: %s", member.node_id, member.name, why)
        for uid in member.pubs:  # out of every table first: then tell the others
            self._discard(self._publishers, uid, member.node_id)
        for uid in member.subs:
            self._discard(self._subscribers, uid, member.node_id)
        self._watches.forget(member.node_id)  # its pattern subscriptions: publishers are told
        for uid in member.pubs:
            self._vouch(uid, member)
        for uid in member.subs:
            self._push(uid)
        link, member.link = member.link, None
        if link is not None:
            link.abort(why)

    def _discard(self, table: dict[int, set[int]], uid: int, node_id: int) -> None:
        nodes = table.get(uid)
        if nodes is not None:
            nodes.discard(node_id)
            if not nodes:
                del table[uid]
                if uid not in self._subscribers and uid not in self._publishers:
                    self._channel_count -= 1
                    if self._names.pop(uid, None) is not None:
                        self._watches.unnamed(uid)

    # --- telling nodes ---------------------------------------------------------------------

    def _subscribers_of(self, uid: int) -> set[int] | frozenset[int]:
        """The nodes that subscribe to ``uid``: by name or UID, and by a pattern (``_watches``)."""
        exact, implied = self._subscribers.get(uid, _NONE), self._watches.implied(uid)
        return exact | implied if implied else exact

    def _subscribers_frame(self, uid: int) -> bytes:
        peers = tuple(self._members[n].peer() for n in sorted(self._subscribers_of(uid)))
        return w.encode(w.Subscribers(uid, peers))

    def _identities(self, uid: int) -> tuple[tuple[int, str], ...]:
        """The nodes that publish on ``uid``, with their identities (none without TLS)."""
        members = (self._members[n] for n in self._publishers.get(uid, ()))
        return tuple(sorted((m.node_id, m.identity) for m in members if m.identity is not None))

    def _answer(self, member: Member, uid: int, subscribe: bool) -> None:
        """Send a subscriber the channel's Publishers, a publisher its Subscribers."""
        if self._recovering:
            self._waiting.setdefault((uid, subscribe), set()).add(member.node_id)
        elif member.link is not None:
            frame = (
                w.encode(w.Publishers(uid, self._identities(uid)))
                if subscribe
                else self._subscribers_frame(uid)
            )
            member.link.send_control(frame)  # never dropped: a node that leaves too many
            # unread is cut off by its link

    def _push(self, uid: int, skip: int | None = None) -> None:
        """Tell the publishers of ``uid`` its new subscriber list."""
        for node_id in self._publishers.get(uid, ()):
            if node_id != skip:
                self._answer(self._members[node_id], uid, subscribe=False)
                self.counters["pushes"] += 1

    def _vouch(self, uid: int, publisher: Member) -> None:
        """``publisher`` came to or left ``uid``: tell the channel's subscribers its new
        Publishers (without TLS there are no identities to tell)."""
        if publisher.identity is None:
            return
        for node_id in self._subscribers_of(uid):
            self._answer(self._members[node_id], uid, subscribe=True)
            self.counters["pushes"] += 1

    async def _end_recovery(self) -> None:
        await asyncio.sleep(self.recovery)
        self._recovering = False
        waiting, self._waiting = self._waiting, {}
        for (uid, subscribe), node_ids in waiting.items():
            for node_id in node_ids:
                member = self._members.get(node_id)
                if member is not None:
                    self._answer(member, uid, subscribe)
        log.info("TCP-ECB recovered: %d nodes registered", len(self._members))


_NONE: frozenset[int] = frozenset()


async def serve(
    listen: str, liveness: float, recovery: float, tls: Tls | None = None, acl: Acl | None = None,
    metrics: str | None = None, identities: Path | None = None,
) -> None:  # fmt: skip
    """Run a TCP-ECB on ``listen`` (HOST:PORT) until cancelled; with ``metrics`` (HOST:PORT),
    its counters are served there to Prometheus; ``identities``: see ``TcpEcb``."""
    from ups._metrics import serving_metrics

    from ._metrics import tcp_ecb_reading

    host, port = parse_address(listen)
    ecb = TcpEcb(host, port, liveness=liveness, recovery=recovery, tls=tls, acl=acl,
                 identities=identities)  # fmt: skip
    async with serving_metrics(metrics, "broker", lambda: tcp_ecb_reading(ecb.stats())):
        await ecb.start()
        try:
            await asyncio.Event().wait()
        finally:
            await ecb.close()
