"""What a recording must never do, over random histories of a bus: read an event as another
channel's. Etags are bound and bound anew at random, the recording starts at a random moment
(what was bound before comes from the CAN-ECB's tables, as ``ups record`` loads them), and
every python-can format is written and read back with python-can's own writers and readers."""

from __future__ import annotations

import tempfile
from pathlib import Path

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ups import _canproto as p
from ups._bindings import Bindings, Event
from ups.tools.decode import Tally, bindings_for, read
from ups.tools.record import FORMATS, _Recorder

ETAGS = st.integers(p.FIRST_ETAG, p.FIRST_ETAG + 3)
UIDS = st.integers(1, 6)
TXNODES = st.integers(0, 2)
STEP = st.one_of(
    st.tuples(st.just("bind"), ETAGS, UIDS),
    st.tuples(st.just("assign"), TXNODES, st.integers(0xA0, 0xA3)),  # node ids
    st.tuples(st.just("event"), ETAGS, st.tuples(TXNODES, st.binary(max_size=8))),
    st.tuples(st.just("noise"), st.integers(0, 0x7FF), st.binary(max_size=8)),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(history=st.lists(STEP, max_size=40), suffix=st.sampled_from(FORMATS), data=st.data())
def test_every_recorded_event_reads_as_the_channel_and_node_it_was_sent_on(
    history: list[tuple[str, int, object]], suffix: str, data: st.DataObject
) -> None:
    start = data.draw(st.integers(0, len(history)), label="start")
    bound: dict[int, int] = {}  # the bus's bindings, step by step
    nodes: dict[int, int] = {}  # TxNode -> node id, step by step
    expected: list[tuple[int | None, int | None]] = []  # channel and node of each event
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / f"run{suffix}")
        recorder: _Recorder | None = None
        for i, (kind, key, value) in enumerate([*history, ("end", 0, b"")]):
            if i == start or (recorder is None and kind == "end"):
                tables = Bindings(etags=dict(bound), txnodes=dict(nodes))  # the CAN-ECB's
                recorder = _Recorder(path, set(), tables, None)
                recorder.started = True  # as ups record says "recording ..."
            t = float(i)
            if kind == "bind":
                assert isinstance(value, int)
                bound[key] = value
                can_id, data = p.encode(p.Bind(key, value))
                msg = can.Message(timestamp=t, arbitration_id=can_id, data=data)
            elif kind == "assign":  # a node has one TxNode: its old one is no longer its
                assert isinstance(value, int)
                for txnode in [t for t, n in nodes.items() if n == value]:
                    del nodes[txnode]
                nodes[key] = value
                can_id, data = p.encode(p.Assign(key, value))
                msg = can.Message(timestamp=t, arbitration_id=can_id, data=data)
            elif kind == "event":
                assert isinstance(value, tuple)
                txnode, payload = value
                can_id = p.make_id(p.DEFAULT_PRIORITY, txnode, key)
                msg = can.Message(timestamp=t, arbitration_id=can_id, data=payload)
                if recorder is not None:
                    expected.append((bound.get(key), nodes.get(txnode)))
            elif kind == "noise":  # 11-bit traffic of another protocol
                assert isinstance(value, bytes)
                msg = can.Message(timestamp=t, arbitration_id=key, data=value,
                                  is_extended_id=False)  # fmt: skip
            else:
                break
            if recorder is not None:
                recorder.frame(msg)
        assert recorder is not None
        recorder.close()
        tally = Tally()
        bindings = bindings_for(path, None, None)
        got = [
            (item.uid, bindings.txnodes.get(item.txnode))
            for _, item in read(path, bindings, tally)
            if isinstance(item, Event)
        ]
    assert got == expected
    unbound = [uid for uid, _ in expected if uid is None]
    assert tally.unbound == len(unbound)  # an event never bound is shown as unbound
