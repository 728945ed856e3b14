"""libups-ecb's admission analysis (c/ups_ecb_rt.c) against the Python one (ups/rt, used by
broker/_admission.py): paper 000's Table 1 cell by cell, and the same verdicts, priorities, miss
and response as ``Admission.decide`` on random declarations, also under ASan and UBSan.

``test_admission_under_sanitizers`` runs the property in a child process on
``libups-ecb-asan.so`` (``UPS_CECB_RT=asan``): ASan's runtime must be preloaded into Python.
"""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
from fractions import Fraction
from functools import cache
from pathlib import Path

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from ups import _canproto as p
from ups._cnode import build
from ups.broker._admission import RT_FIRST, RT_LAST, Admission
from ups.rt import MessageSpec, analyze, assign_priorities, load_csv

from .procs import sanitizer_env
from .rt.conftest import SAE_CSV
from .rt.test_rt_analysis import BITRATES, _table_1

VARIANT = os.environ.get("UPS_CECB_RT", "full")
TARGETS = {"full": "libups-ecb.so", "asan": "libups-ecb-asan.so"}
SOURCES = ("ups.h", "ups_ecb.h", "ups_ecb_internal.h", "ups_ecb_rt.h", "ups_ecb_join.h",
           "ups_ecb_bind.h", "ups_ecb_elect.h", "ups_ecb_util.c", "ups_ecb_rt.c", "ups_ecb.c",
           "ups_ecb_join.c", "ups_ecb_bind.c", "ups_ecb_elect.c", "host/ups_ecb_host.c",
           "Makefile")  # fmt: skip
TINDELL1994, FD, ID11 = 1, 2, 4  # ups_ecb_rt.h's UPS_ECB_RT_* flags
UNBOUNDED = 2**64 - 1
RT_MAX = 127  # UPS_ECB_RT_MAX


class Stream(ctypes.Structure):
    """ups_ecb_stream_t."""

    _fields_ = [
        ("etag", ctypes.c_uint16),
        ("txnode", ctypes.c_uint8),
        ("size", ctypes.c_uint8),
        ("period", ctypes.c_uint16),
        ("deadline", ctypes.c_uint16),
        ("jitter", ctypes.c_uint8),
        ("priority", ctypes.c_uint8),
    ]


@cache
def _lib() -> ctypes.CDLL:
    lib = ctypes.CDLL(str(build(VARIANT, targets=TARGETS, sources=SOURCES)))
    lib.ups_ecb_rt_admit.restype = ctypes.c_int
    lib.ups_ecb_rt_admit.argtypes = [
        ctypes.POINTER(Stream), ctypes.c_uint, ctypes.c_uint32, ctypes.c_uint,
        ctypes.POINTER(ctypes.c_uint), ctypes.POINTER(ctypes.c_uint16),
    ]  # fmt: skip
    lib.ups_ecb_rt_response.restype = ctypes.c_uint64
    lib.ups_ecb_rt_response.argtypes = [
        ctypes.POINTER(Stream), ctypes.c_uint, ctypes.c_uint32, ctypes.c_uint,
        ctypes.POINTER(ctypes.c_uint64),
    ]  # fmt: skip
    return lib


def _tenths(ms: Fraction) -> int:
    units = ms * 10
    assert units.denominator == 1, ms
    return int(units)


def c_analyze(
    rows: list[tuple[int, int, int, int]], bitrate: int, flags: int
) -> list[Fraction | None]:
    """ups_ecb_rt_response on (bytes, period, deadline, jitter) rows (x 100 us), highest first."""
    streams = (Stream * len(rows))(
        *(Stream(0x100 + i, 1, size, t, d, j, 0) for i, (size, t, d, j) in enumerate(rows))
    )
    out = (ctypes.c_uint64 * len(rows))()
    per_ms = _lib().ups_ecb_rt_response(streams, len(rows), bitrate, flags, out)
    assert per_ms > 0
    return [None if r == UNBOUNDED else Fraction(r, per_ms) for r in out]


def _sae_rows() -> list[tuple[int, int, int, int]]:
    return [
        (s.size_bytes, _tenths(s.period_ms), _tenths(s.deadline_ms), _tenths(s.jitter_ms))
        for s in load_csv(SAE_CSV)
    ]


@pytest.mark.parametrize("column", range(4), ids=[f"{b // 1000}kbit" for b in BITRATES])
def test_c_reproduces_table_1(column: int) -> None:
    """Every cell of paper 000's Table 1 (53 messages, tindell1994, 11-bit identifiers): the
    response time, or none, and the deadline mark, as tests/rt's check of ups/rt."""
    rows = _sae_rows()
    table = _table_1()
    assert len(table) == len(rows) == 53
    got = c_analyze(rows, BITRATES[column], TINDELL1994 | ID11)
    for (name, cells), (_, _, deadline, _), r in zip(table, rows, got, strict=True):
        met = r is not None and r <= Fraction(deadline, 10)
        assert (r, met) == cells[column], name


@pytest.mark.parametrize("bitrate", [50_000, 125_000, 333_333, 500_000, 1_000_000])
@pytest.mark.parametrize("flags", [0, ID11, FD, FD | ID11, TINDELL1994])
def test_c_analysis_is_python_analysis_on_sae(bitrate: int, flags: int) -> None:
    """Both methods, both identifier lengths, classic and FD: every response of the SAE set."""
    specs = load_csv(SAE_CSV)
    id_bits, fd = 11 if flags & ID11 else 29, bool(flags & FD)
    if flags & TINDELL1994:
        expected = analyze(specs, bitrate, "tindell1994", id_bits, fd=fd)
    else:
        expected = analyze(specs, bitrate, "davis2007", id_bits, fd=fd)
    assert c_analyze(_sae_rows(), bitrate, flags) == [r.response_time_ms for r in expected]


def c_admit(
    candidate: dict[tuple[int, int], p.Declare], bitrate: int, fd: bool
) -> p.Refuse | dict[tuple[int, int], int] | tuple[int, int]:
    """ups_ecb_rt_admit on the streams sorted by (etag, TxNode): the priorities, or a Refuse
    naming the miss (its etag and txnode fields 0), or (miss index, 0) for Python's ValueError."""
    keys = sorted(candidate)
    streams = (Stream * len(keys))(
        *(
            Stream(m.etag, m.txnode, m.size_bytes, m.period, m.deadline, m.jitter, 0)
            for m in (candidate[k] for k in keys)
        )
    )
    miss, response = ctypes.c_uint(), ctypes.c_uint16()
    admitted = _lib().ups_ecb_rt_admit(
        streams, len(keys), bitrate, int(fd), ctypes.byref(miss), ctypes.byref(response)
    )
    if admitted:
        return {k: s.priority for k, s in zip(keys, streams, strict=True)}
    if response.value == 0:
        return (miss.value, 0)
    return p.Refuse(0, 0, *keys[miss.value], response.value)


def check_declarations(
    declarations: list[p.Declare], bitrate: int, fd: bool, *, events: bool = False
) -> None:
    """Declare one after the other on a Python Admission; before each, the C analysis of the
    same candidate set must give Python's verdict (``events``: tell Hypothesis which)."""
    python = Admission(bitrate, fd)
    asked: dict[tuple[int, int], p.Declare] = {}
    for msg in declarations:
        key = (msg.etag, msg.txnode)
        candidate = {**asked, key: msg}
        got = c_admit(candidate, bitrate, fd)
        verdict = python.decide(msg)
        if events:
            refused = verdict.frames[0]
            event(
                "admitted" if not isinstance(refused, p.Refuse)
                else f"refused: {'unbounded' if refused.response_10us == 0xFFFF else 'bounded'}"
            )  # fmt: skip
        if verdict.admitted:
            assert got == python.granted, msg
            asked = candidate
        else:
            [refuse] = verdict.frames
            assert isinstance(refuse, p.Refuse)
            if refuse.response_10us == 0:  # ValueError: more streams than priorities
                assert got == (len(candidate) - 1, 0)
            else:
                assert got == p.Refuse(0, 0, refuse.miss_etag, refuse.miss_txnode,
                                       refuse.response_10us), msg  # fmt: skip


def _period() -> st.SearchStrategy[int]:
    return st.one_of(st.integers(1, 200), st.integers(200, 5_000), st.integers(1, 65_535))


def _declare(
    etag: int, size: int, period: int, deadline: int | None, jitter: int, txnode: int
) -> p.Declare:
    return p.Declare(txnode, etag, size, period, period if deadline is None else deadline, jitter)


def _stream(
    etags: st.SearchStrategy[int], sizes: st.SearchStrategy[int]
) -> st.SearchStrategy[p.Declare]:
    """Deadlines equal to the period (None) or drawn; jitter mostly 0."""
    return st.builds(
        _declare, etags, sizes, _period(), st.one_of(st.none(), _period()),
        st.one_of(st.just(0), st.integers(0, 255)), st.integers(1, 8),
    )  # fmt: skip


_any_stream = st.one_of(
    _stream(st.integers(0x0100, 0x0140), st.integers(0, 8)),
    _stream(
        st.integers(p.LARGE_FIRST_ETAG, p.LARGE_FIRST_ETAG + 40),
        st.one_of(st.integers(1, 4), st.integers(1, 255)),
    ),
)
#: 1..32 declarations, as many of each count
declarations = st.integers(1, 32).flatmap(lambda n: st.lists(_any_stream, min_size=n, max_size=n))


BUS = st.tuples(
    st.one_of(
        st.sampled_from([10_000, 125_000, 250_000, 500_000, 1_000_000, 2_000_000, 8_000_000]),
        st.integers(10_000, 8_000_000),
    ),
    st.booleans(),
)
EXAMPLES = int(os.environ.get("UPS_CECB_RT_EXAMPLES", "200" if VARIANT == "asan" else "300"))


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(declarations, BUS)
def test_admission_is_pythons(declared: list[p.Declare], bus: tuple[int, bool]) -> None:
    """Declarations one after the other: each verdict, every priority, the miss and the
    response of ups_ecb_rt_admit are those of broker/_admission.py's Admission.decide."""
    check_declarations(declared, *bus, events=True)


def test_admission_of_classic_examples() -> None:
    """Fixed cases: a lone stream, one that cannot fit (unbounded), a jittered pair, a
    transfer of 255 frames on a slow bus, FD."""
    check_declarations([p.Declare(1, 0x100, 8, 10, 10, 0)], 500_000, False)
    check_declarations([p.Declare(1, 0x100, 8, 1, 1, 0)], 10_000, False)
    check_declarations(
        [p.Declare(1, 0x100, 8, 10, 5, 3), p.Declare(2, 0x101, 2, 10, 4, 255),
         p.Declare(3, 0x3000, 255, 65_535, 65_535, 0), p.Declare(3, 0x3001, 20, 1000, 200, 0)],
        125_000, False,
    )  # fmt: skip
    check_declarations(
        [p.Declare(1, 0x3000, 3, 50, 20, 1), p.Declare(2, 0x100, 8, 5, 5, 0)], 2_000_000, True
    )


# At 10 kbit/s an 8-byte classic frame (29-bit identifier, worst stuffing) takes 160 bits, 16 ms:
# 160 x 100 us. Periods of 160 per stream, 320 for two, 480 for three load the bus exactly fully.
FULL_LOAD = [
    [(8, 160, 65_535, 0)],
    [(8, 320, 65_535, 0), (8, 320, 65_535, 0)],
    [(8, 480, 65_535, 0), (8, 480, 65_535, 0), (8, 480, 65_535, 0)],
    [(8, 161, 65_535, 0)],  # just below: a long busy period, a finite response
    [(8, 321, 65_535, 0), (8, 321, 65_535, 255)],
    [(8, 480, 65_535, 0), (8, 481, 65_535, 7), (8, 479, 65_535, 0)],  # just above
    [(8, 961, 65_535, 3), (8, 479, 65_535, 0), (8, 65_535, 65_535, 255)],
]


@pytest.mark.parametrize("rows", FULL_LOAD)
@pytest.mark.parametrize("bitrate", [10_000, 10_001])
def test_utilisation_at_and_near_one(rows: list[tuple[int, int, int, int]], bitrate: int) -> None:
    """Exactly full (Python: None), just below (finite, long busy periods) and just above, in
    both entries: ups_ecb_rt_response against analyze, ups_ecb_rt_admit against decide."""
    specs = [
        MessageSpec(str(i), size, Fraction(t, 10), Fraction(d, 10), Fraction(j, 10))
        for i, (size, t, d, j) in enumerate(rows)
    ]
    expected = [r.response_time_ms for r in analyze(specs, bitrate)]
    assert c_analyze(rows, bitrate, 0) == expected
    declared = [p.Declare(1, 0x100 + i, *row) for i, row in enumerate(rows)]
    check_declarations(declared, bitrate, False)


def _near_full(count: int, same_deadline: bool) -> list[p.Declare]:
    """c/cycles_ecb.py's costliest stream sets for the admission (500 kbit/s, 95 % of the bus):
    every deadline the same, or rising from 1/count of the period; refused at the lowest level,
    where every candidate's response is then analysed to the end."""
    period = count * 3 * 100 // 95
    return [
        p.Declare(k % 120, 0x10 + k, 8, period + 3 * k, period, 0) if same_deadline
        else p.Declare(k % 120, 0x10 + k, 8, period + k, max(1, period * (k + 1) // count), k % 3)
        for k in range(count)
    ]  # fmt: skip


#: the costliest set a longer search of c/cycles_ecb.py's (400 examples) found for 32 streams, as
#: (etag, TxNode, size, period, deadline, jitter): refused at the lowest level, where each of
#: the 32 candidates has a busy period of many instances (6.8 million cycles on Cortex-M0+)
COSTLIEST_32 = [
    (0x15, 6, 8, 40, 41, 10),
    (0x1b, 12, 6, 46, 47, 16),
    (0x21, 18, 4, 52, 53, 1),
    (0x27, 24, 2, 58, 59, 7),
    (0x2d, 30, 8, 64, 65, 13),
    (0x33, 36, 6, 70, 71, 19),
    (0x39, 42, 4, 76, 77, 4),
    (0x3f, 48, 2, 82, 83, 10),
    (0x45, 54, 8, 88, 89, 16),
    (0x4b, 60, 6, 94, 95, 1),
    (0x51, 66, 4, 100, 101, 7),
    (0x57, 72, 2, 106, 107, 13),
    (0x5d, 78, 8, 112, 113, 19),
    (0x63, 84, 6, 118, 119, 4),
    (0x69, 90, 4, 124, 125, 10),
    (0x6f, 96, 2, 130, 131, 16),
    (0x75, 102, 8, 136, 137, 1),
    (0x7b, 108, 6, 142, 143, 7),
    (0x81, 114, 4, 148, 149, 13),
    (0x87, 120, 2, 154, 155, 19),
    (0x8d, 126, 8, 160, 161, 4),
    (0x93, 5, 6, 166, 167, 10),
    (0x99, 11, 4, 172, 173, 16),
    (0x9f, 17, 2, 178, 179, 1),
    (0xa5, 23, 8, 184, 185, 7),
    (0xab, 29, 6, 190, 191, 13),
    (0xb1, 35, 4, 196, 197, 19),
    (0xb7, 41, 2, 202, 203, 4),
    (0xbd, 47, 8, 208, 209, 10),
    (0xc3, 53, 6, 217, 369, 16),
    (0xc9, 0, 5, 226, 371, 0),
    (0x3ffe, 0, 2, 34, 35, 4),
]  # fmt: skip


@pytest.mark.parametrize("which", ["rising deadlines", "same deadline", "searched"])
def test_admission_of_the_costliest_sets(which: str) -> None:
    """The 32-stream sets that cost ups_ecb_rt_admit the most on Cortex-M0+ (c/cycles_ecb.py), one
    declaration after the other: every verdict, miss and response as Python's."""
    if which == "searched":
        declared = [p.Declare(t, e, size, period, deadline, jitter)
                    for e, t, size, period, deadline, jitter in COSTLIEST_32]  # fmt: skip
    else:
        declared = _near_full(32, which == "same deadline")
    check_declarations(declared, 500_000, False)
    # and the whole set at once, as its cost was measured: the first 31 declared as admitted
    # (on a bus fast enough for them), the last one decided
    *others, last = declared
    fast = Admission(1_000_000_000)
    for msg in others:
        assert fast.decide(msg).admitted
    python = Admission(500_000)
    python.declared = dict(fast.declared)
    [refuse] = python.decide(last).frames
    assert isinstance(refuse, p.Refuse) and refuse.response_10us not in (0, p.RESPONSE_UNBOUNDED)
    got = c_admit({(m.etag, m.txnode): m for m in declared}, 500_000, False)
    assert got == p.Refuse(0, 0, refuse.miss_etag, refuse.miss_txnode, refuse.response_10us)


def test_more_streams_than_priorities() -> None:
    """126 streams get 0x02..0x7F as assign_priorities gives them; 127 that Audsley can order
    do not fit: Python's ValueError (the CAN-ECB's Refuse with response 0), in C response 0
    with the last stream's index."""
    assert RT_FIRST + RT_MAX - 2 == RT_LAST  # 126 priorities
    declared = {(0x100 + i, 1 + i % 100): p.Declare(1 + i % 100, 0x100 + i, 0, 65_535, 65_535, 0)
                for i in range(RT_MAX)}  # fmt: skip
    specs = [
        MessageSpec(f"{key}", 0, Fraction(6553_5, 10), Fraction(6553_5, 10)) for key in declared
    ]
    fitting = dict(list(declared.items())[:-1])
    values = assign_priorities(specs[:-1], 1_000_000, 29, first=RT_FIRST, last=RT_LAST)
    assert c_admit(fitting, 1_000_000, False) == {key: values[f"{key}"] for key in fitting}
    with pytest.raises(ValueError, match="do not fit"):
        assign_priorities(specs, 1_000_000, 29, first=RT_FIRST, last=RT_LAST)
    assert c_admit(declared, 1_000_000, False) == (RT_MAX - 1, 0)


@pytest.mark.timeout(120 + 30)  # the child's own bound below (a busy machine builds slowly)
def test_admission_under_sanitizers() -> None:
    """The property in a child process on libups-ecb-asan.so (ASan and UBSan)."""
    if VARIANT == "asan":
        pytest.skip("this is the child")
    lib = build("asan", targets=TARGETS, sources=SOURCES)
    env = {**os.environ, "UPS_CECB_RT": "asan", **sanitizer_env()}
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-s", "-x", "-p", "no:cacheprovider",
         "-p", "no:xdist", f"{Path(__file__)}::test_admission_is_pythons",
         f"{Path(__file__)}::test_more_streams_than_priorities"],
        env=env, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    output = done.stdout[-6000:] + done.stderr[-6000:]
    assert done.returncode == 0, f"{lib}:\n{output}"
    assert "2 passed" in done.stdout, output
