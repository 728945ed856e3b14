"""Restarts and recovery ("Restarts, recovery and the answer to Hello", "Durable state")."""

from __future__ import annotations

from pathlib import Path

from ups import name_to_uid

from ._frames import PUB_BIND, SUB_BIND, Assign, Bind, Hello, Serving
from ._wire import RawNode, Wire, serving_ecb

U1, U2, U3, U_NEW = (name_to_uid(f"conformance/recovery/{n}") for n in ("1", "2", "3", "new"))


async def test_empty_ecb_adopts_what_joined_nodes_report(
    raw: Wire, channel: str, tmp_path: Path, ecb_kind: str
) -> None:
    # two joined nodes from a previous run of the bus; they answer Hello as the document says
    a = RawNode(raw, 0xA1, txnode=0x00)
    a.subs = {U1: 0x10}
    a.pubs = {U2: 0x11}
    b = RawNode(raw, 0xB2, txnode=0x02)
    b.subs = {U3: 0x13}
    b.pubs = {U1: 0x10}
    reported = {0x10, 0x11, 0x13}

    async with serving_ecb(channel, tmp_path / "ecb.db", ecb_kind):
        i_hello, _ = await raw.expect(Hello)
        # a new UID is held until recovery ends, then bound to an etag nobody reported
        new = await b.ask(SUB_BIND, U_NEW, timeout=3.0)
        assert new.etag not in reported
        assert new.etag == 0x12, "the lowest free etag once the reported ones are adopted"
        i_new, _ = await raw.expect(Bind(new.etag, U_NEW))
        # (but the Serving that ends the candidacy: "More than one CAN-ECB")
        answers = [f for f in raw.heard(i_hello + 1, i_new) if not isinstance(f, Serving)]
        assert answers == [], "adoption needs no answer"

        # the reported etags were adopted
        assert (await a.ask(SUB_BIND, U1)).etag == 0x10
        assert (await a.ask(PUB_BIND, U2)).etag == 0x11
        assert (await b.ask(SUB_BIND, U3)).etag == 0x13
        assert (await b.ask(SUB_BIND, U2)).etag == 0x11
        # and the claimed TxNodes: a new joiner gets the lowest one nobody claimed
        c = RawNode(raw, 0xC3)
        assert await c.join() == 0x01


async def test_restarted_ecb_keeps_its_table_and_corrects_contradictions(
    raw: Wire, channel: str, tmp_path: Path, ecb_kind: str
) -> None:
    db = tmp_path / "ecb.db"
    a = RawNode(raw, 0xA1)
    async with serving_ecb(channel, db, ecb_kind):
        ta = await a.join()
        etag = (await a.ask(SUB_BIND, U1)).etag
        other_etag = (await a.ask(PUB_BIND, U2)).etag

    # a stray node claims A's TxNode and reports U3 at U1's etag
    stray = RawNode(raw, 0xC3, txnode=ta)
    stray.subs = {U3: etag}
    restart = raw.mark()
    async with serving_ecb(channel, db, ecb_kind):
        i_hello, _ = await raw.expect(Hello, since=restart)
        # "otherwise sends Assign(t', id), t' being id's TxNode in its table or a free one"
        _, moved = await raw.expect(
            lambda f: isinstance(f, Assign) and f.node_id == 0xC3, since=i_hello
        )
        assert moved.txnode != ta and 0 <= moved.txnode <= 0x7E
        # "otherwise sends the Binds of its table for that etag and that UID"
        await raw.expect(Bind(etag, U1), since=i_hello)
        stray.close()
        assert not raw.find(lambda f: isinstance(f, Assign) and f.node_id == 0xA1, i_hello)

        # during recovery a UID in the table is answered at once, a new one when it ends
        since = raw.send(a.request(SUB_BIND, U_NEW), a.request(SUB_BIND, U1))
        i_known, _ = await raw.expect(Bind(etag, U1), since=since)
        i_new, new = await raw.expect(lambda f: isinstance(f, Bind) and f.uid == U_NEW, since=since)
        assert i_known < i_new
        assert new.etag not in (etag, other_etag)
        assert (await a.ask(PUB_BIND, U2)).etag == other_etag

        # a restarted node gets its old TxNode back
        assert await RawNode(raw, 0xA1).join() == ta
