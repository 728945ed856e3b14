"""Scraping a daemon's ``--metrics`` as Prometheus does, and docs/metrics.md as a reader does."""

from __future__ import annotations

import re
import time
import urllib.request
from collections.abc import Callable, Mapping, Sequence
from importlib.metadata import version
from typing import Any, NamedTuple

from prometheus_client.parser import text_string_to_metric_families

from ups._metrics import BUILD_INFO, CAN_LINK, METRICS_PORT, NODE, Metric
from ups.broker._metrics import CAN_ECB, STATUS_PORT, TCP_ECB
from ups.gateway._metrics import gateway_table
from ups.jaus._metrics import JAUS
from ups.ros2._serve import ROS2
from ups.tools.console import CONSOLE

from .procs import ROOT, Proc

DOC = ROOT / "docs" / "metrics.md"
VERSION = version("ups-pubsub")  #: what ups_build_info says

#: every table of the code, with the labels the daemons add to its samples
TABLES: list[tuple[list[Metric], tuple[str, ...]]] = [
    (NODE, ("network",)),
    (CAN_LINK, ()),
    (METRICS_PORT, ()),
    (TCP_ECB, ()),
    (CAN_ECB, ()),
    (STATUS_PORT, ()),
    (gateway_table("SIDE"), ()),
    (JAUS, ()),
    (ROS2, ()),
    (CONSOLE, ()),
]


class Row(NamedTuple):
    """A metric as docs/metrics.md lists it."""

    name: str
    kind: str
    labels: str
    source: str
    meaning: str


def documented() -> dict[str, Row]:
    """The rows of every table of docs/metrics.md, by name."""
    rows: dict[str, Row] = {}
    for line in DOC.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and re.fullmatch(r"`(ups|process)_\w+`", cells[0]):
            assert len(cells) == 5, line
            row = Row(cells[0].strip("`"), *cells[1:])
            assert row.name not in rows, f"{row.name} is listed twice"
            rows[row.name] = row
    return rows


def rows_of_code() -> dict[str, Row]:
    """What docs/metrics.md must say of each metric of the code's tables."""
    families: dict[str, list[tuple[Metric, tuple[str, ...]]]] = {}
    for metrics, extra in TABLES:
        for m in metrics:
            families.setdefault(m.name, []).append((m, extra))
    rows = {}
    for name, members in families.items():
        first = members[0][0]
        assert {(m.kind, m.help) for m, _ in members} == {(first.kind, first.help)}, name
        labels = sorted({k for m, extra in members for k in (*(k for k, _ in m.labels), *extra)})
        sources = [
            f"`{m.key}`" + (f" ({', '.join(f'{k}={v}' for k, v in m.labels)})" if m.labels else "")
            for m, _ in members
        ]
        rows[name] = Row(name, first.kind, ", ".join(f"`{k}`" for k in labels),
                         ", ".join(sources), first.help)  # fmt: skip
    name, kind, text, labels = BUILD_INFO
    rows[name] = Row(name, kind, ", ".join(f"`{k}`" for k in labels), "the installed release", text)
    return rows


class Scrape:
    """One scrape: every sample as (name, labels) -> value, and each sample's family type."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.values: dict[tuple[str, frozenset[tuple[str, str]]], float] = {}
        self.kinds: dict[str, tuple[str, tuple[str, ...]]] = {}  # name -> type, label names
        for family in text_string_to_metric_families(text):
            for s in family.samples:
                self.values[(s.name, frozenset(s.labels.items()))] = s.value
                self.kinds[s.name] = (family.type, tuple(sorted(s.labels)))

    def value(self, name: str, **labels: str) -> float:
        key = (name, frozenset(labels.items()))
        assert key in self.values, f"no {name}{labels or ''} in the scrape:\n{self.text}"
        return self.values[key]

    def get(self, name: str, default: float = -1.0, **labels: str) -> float:
        return self.values.get((name, frozenset(labels.items())), default)

    def undocumented(self) -> list[str]:
        """The samples not listed in docs/metrics.md with their type and label names."""
        rows = documented()
        wrong = []
        for name, (kind, labels) in sorted(self.kinds.items()):
            row = rows.get(name)
            names = ", ".join(f"`{k}`" for k in labels)
            if row is None or (row.kind, row.labels) != (kind, names):
                wrong.append(f"{name} ({kind}, labels {names or 'none'}): {row}")
        return wrong


def scrape(url: str) -> Scrape:
    with urllib.request.urlopen(url, timeout=15) as response:
        assert response.headers["Content-Type"].startswith("text/plain; version=0.0.4")
        return Scrape(response.read().decode())


def scrape_until(url: str, ready: Callable[[Scrape], bool], timeout: float = 60.0) -> Scrape:
    """Scrape until ``ready`` says the traffic has been counted; fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        found = scrape(url)
        if ready(found):
            return found
        if time.monotonic() > deadline:
            raise AssertionError(f"the metrics did not get there within {timeout} s:\n{found.text}")
        time.sleep(0.1)


def metrics_url(proc: Proc) -> str:
    """Where ``proc`` (started with ``--metrics 127.0.0.1:0``) said it serves its metrics."""
    pattern = r"metrics on (http://127\.0\.0\.1:\d+/metrics)"
    for line in list(proc.stderr_lines):
        if found := re.search(pattern, line):
            return found.group(1)
    found = re.search(pattern, proc.wait_for_line(pattern, timeout=60))
    assert found is not None
    return found.group(1)


def uncovered(
    stats: Mapping[str, Any], tables: Sequence[list[Metric]], unexposed: Mapping[str, str] = {}
) -> set[str]:
    """The numbers of ``stats`` (as ``ups status`` shows them) that no table reads and that
    are not named as left out."""
    read = {m.key for t in tables for m in t}
    numbers = {k for k, v in stats.items() if isinstance(v, bool | int | float)}
    return numbers - read - set(unexposed)
