"""Fixtures of the conformance suite: a virtual bus of the test's own, a raw wire on it, and
our CAN-ECB serving it, each test once per CAN-ECB (``ecb_kind``: ids end in ``[python]``,
``[c]`` and, for the tests of ``M0``, ``[m0]``)."""

from __future__ import annotations

import importlib.util
import itertools
import os
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from ._frames import Foreign, Hello, Malformed
from ._wire import ECBS, Ecb, Wire, serving_ecb

_numbers = itertools.count()

#: the tests run against the emulated Cortex-M0+ image too (``[m0]``): one or two of each file,
#: as the whole suite on it costs about a minute more (its waits are the other kinds'); with
#: UPS_CONFORMANCE_M0=all every test runs on it (``M0_UNFIT`` excepted)
M0 = {
    "test_raw_joiner_gets_census_then_assign",
    "test_two_joiners_get_distinct_txnodes_after_a_query_per_branch",
    "test_a_node_joining_again_gets_its_txnode_back",
    "test_sub_bind_and_pub_bind_are_answered_with_binds",
    "test_raw_events_reach_a_subscribed_node",
    "test_declare_is_granted_and_an_identical_declare_gets_the_same_grant",
    "test_ecb_answers_a_contradicting_bind_with_its_own_binds",
    "test_malformed_management_frames_are_ignored",
    "test_empty_ecb_adopts_what_joined_nodes_report",
    "test_restarted_ecb_keeps_its_table_and_corrects_contradictions",
    "test_the_roster_lists_who_subscribes_and_publishes",
    "test_serving_of_a_lower_instance_makes_it_stand_by",
    "test_a_request_unanswered_while_it_stands_by_makes_it_serve_whatever_servings_say",
    "test_a_flood_of_strays_claims_cannot_lock_a_new_node_out",
    "test_a_flood_of_moves_cannot_lock_a_new_node_out",
    "test_a_node_on_probation_moved_back_to_its_own_txnode_stays_on_probation",
}
M0_UNFIT = {  # test -> why the ecb-full image cannot pass it
    "test_ecb_refuses_bindings_past_a_node_ids_quota_and_binds_what_exists": "the ecb-full "
    "image binds 512 channels, fewer than one node id's quota of 1024",
}


@pytest.fixture
def channel(request: pytest.FixtureRequest) -> str:
    """A python-can virtual channel name of this test's own."""
    return f"conformance-{request.node.name}-{os.getpid()}-{next(_numbers)}"


@pytest.fixture
async def raw(channel: str) -> AsyncIterator[Wire]:
    """The test's raw bus, opened before anything else so that it hears every frame."""
    wire = Wire(channel)
    yield wire
    await wire.close()
    bad = wire.find((Malformed, Foreign))
    assert not bad, f"our CAN-ECB or node sent frames the document does not define: {bad}"


@pytest.hookimpl(trylast=True)  # after the tests' own parameters: ids end in [python], [c]
def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "ecb_kind" in metafunc.fixturenames:
        name = metafunc.function.__name__
        m0 = name in M0 or os.environ.get("UPS_CONFORMANCE_M0") == "all"
        marks = []
        if name in M0_UNFIT:
            marks.append(pytest.mark.skip(reason=M0_UNFIT[name]))
        elif importlib.util.find_spec("unicorn") is None:
            marks.append(pytest.mark.skip(reason="the emulator needs unicorn (the emu extra)"))
        kinds = [k if k != "m0" else pytest.param(k, marks=marks) for k in ECBS]
        metafunc.parametrize("ecb_kind", kinds if m0 else [k for k in ECBS if k != "m0"],
                             indirect=True)  # fmt: skip


@pytest.fixture
def ecb_kind(request: pytest.FixtureRequest) -> str:
    """Which CAN-ECB serves the test's bus: "python" (broker/can_ecb.py), "c" (libups-ecb,
    c/ups_ecb.h, through broker/c_ecb.py) or "m0" (libups-ecb's Cortex-M0+ image in an
    emulator, the same loop). Every test that uses ``can_ecb``, or makes a CAN-ECB with
    ``serving_ecb(..., ecb_kind)``, runs against the first two, those of ``M0`` against the
    third too; its id ends in ``[python]``, ``[c]`` or ``[m0]`` (``[<other parameters>-c]``
    when it has more). To run only the C one:

        .venv/bin/python -m pytest tests/conformance -m c_ecb

    (or ``-m python_ecb``, ``-m m0_ecb``; ``-k "c]"`` selects the same by id)."""
    return str(request.param)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        kind = getattr(item, "callspec", None) and item.callspec.params.get("ecb_kind")
        if kind:
            item.add_marker(getattr(pytest.mark, f"{kind}_ecb"))


def pytest_configure(config: pytest.Config) -> None:
    for kind in ECBS:
        config.addinivalue_line("markers", f"{kind}_ecb: runs against the {kind} CAN-ECB")


@pytest.fixture
async def can_ecb(raw: Wire, channel: str, tmp_path: Path, ecb_kind: str) -> AsyncIterator[Ecb]:
    """Our CAN-ECB (``ecb_kind``) on the test's bus, with an empty table and a 0.2 s recovery
    window."""
    async with serving_ecb(channel, tmp_path / "ecb.db", ecb_kind) as ecb:
        yield ecb


@pytest.fixture
async def instance(raw: Wire, can_ecb: Ecb) -> int:
    """The instance of the CAN-ECB, read from its Hello on the wire."""
    _, hello = await raw.expect(Hello)
    return int(hello.instance)
