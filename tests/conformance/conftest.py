"""Fixtures of the conformance suite: a virtual bus of the test's own, a raw wire on it, and
our CAN-ECB serving it, each test once per CAN-ECB (``ecb_kind``: ids end in ``[python]`` and
``[c]``)."""

from __future__ import annotations

import itertools
import os
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from ._frames import Foreign, Hello, Malformed
from ._wire import ECBS, Ecb, Wire, serving_ecb

_numbers = itertools.count()


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
        metafunc.parametrize("ecb_kind", ECBS, indirect=True)


@pytest.fixture
def ecb_kind(request: pytest.FixtureRequest) -> str:
    """Which CAN-ECB serves the test's bus: "python" (broker/can_ecb.py) or "c" (libups-ecb,
    c/ups_ecb.h, through broker/c_ecb.py). Every test that uses ``can_ecb``, or makes a CAN-ECB
    with ``serving_ecb(..., ecb_kind)``, runs against both; its id ends in ``[python]`` or
    ``[c]`` (``[<other parameters>-c]`` when it has more). To run only the C one:

        .venv/bin/python -m pytest tests/conformance -m c_ecb

    (or ``-m python_ecb``; ``-k "c]"`` selects the same by id)."""
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
