"""Fixtures of the conformance suite: a virtual bus of the test's own, a raw wire on it, and
our CAN-ECB serving it."""

from __future__ import annotations

import itertools
import os
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from ups.broker.can_ecb import CanEcb

from ._frames import Foreign, Hello, Malformed
from ._wire import Wire, serving_ecb

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


@pytest.fixture
async def can_ecb(raw: Wire, channel: str, tmp_path: Path) -> AsyncIterator[CanEcb]:
    """Our CAN-ECB on the test's bus, with an empty table and a 0.2 s recovery window."""
    async with serving_ecb(channel, tmp_path / "ecb.db") as ecb:
        yield ecb


@pytest.fixture
async def instance(raw: Wire, can_ecb: CanEcb) -> int:
    """The instance of the CAN-ECB, read from its Hello on the wire."""
    _, hello = await raw.expect(Hello)
    return int(hello.instance)
