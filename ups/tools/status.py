"""``ups status``'s readable form: a daemon's or node's Status (the JSON ``ups status --json``
prints) as a terminal shows it.

Any Status renders, whatever answered (a TCP-ECB, a gateway, a node, every node of a Zenoh
network), because the form follows the document's shape, not a list of known fields: scalars
as ``key: value`` lines, a table of counters as the counters that are not zero (the rest
counted, not listed: a counter that stays 0 is what a healthy daemon shows), a list of records
as an aligned table (a list inside a record as its length), and channel UIDs with their names
where the document names them.
"""

from __future__ import annotations

import textwrap
from typing import Any

WIDTH = 100
MAX_LISTED = 8  # scalars of a list shown before "... N more"


def render(info: dict[str, Any] | list[dict[str, Any]]) -> str:
    """The whole Status (or, from Zenoh, every node's) as text for a terminal."""
    if isinstance(info, list):
        if not info:
            return "no UPS node or gateway answered"
        return "\n\n".join(render(one) for one in info)
    info = dict(info)
    names = {c["uid"]: c["name"] for c in info.get("channels") or [] if c.get("name")}
    title = " ".join(str(info[k]) for k in ("name", "node_id") if info.get(k))
    if info.get("address"):
        title += f" at {info['address']}"
    rest = {k: v for k, v in info.items() if k not in ("name", "node_id", "address")}
    return "\n".join([title or "status", *_section(rest, names, "  ")])


def _section(doc: dict[str, Any], names: dict[str, str], indent: str) -> list[str]:
    lines: list[str] = []
    scalars = {k: v for k, v in doc.items() if not isinstance(v, dict | list | tuple)}
    counters = {k: v for k, v in scalars.items() if isinstance(v, int) and not isinstance(v, bool)}
    if len(counters) >= 4:  # a table of counters
        shown = ", ".join(f"{k} {v}" for k, v in counters.items() if v)
        zero = sum(1 for v in counters.values() if not v)
        if zero:
            shown += f"; {zero} more at 0" if shown else f"{zero} counters, all 0"
        lines += textwrap.wrap(shown, WIDTH, initial_indent=indent, subsequent_indent=indent + "  ")
        scalars = {k: v for k, v in scalars.items() if k not in counters}
    lines += [f"{indent}{k}: {_value(v, names)}" for k, v in scalars.items()]
    for key, value in doc.items():
        if isinstance(value, dict):
            lines += [f"{indent}{key}:", *_section(value, names, indent + "  ")]
        elif isinstance(value, list | tuple) and value and all(isinstance(v, dict) for v in value):
            lines += [f"{indent}{key} ({len(value)}):", *_table(list(value), names, indent + "  ")]
        elif isinstance(value, list | tuple):
            lines.append(f"{indent}{key}: {_listed(value, names) if value else '-'}")
    return lines


def _table(records: list[dict[str, Any]], names: dict[str, str], indent: str) -> list[str]:
    """The records as an aligned table, one column per key (nested records left out)."""
    columns = list(dict.fromkeys(k for r in records for k in r if not isinstance(r[k], dict)))
    rows = [[c.upper() for c in columns]]
    rows += [[_cell(r.get(c), {} if c == "uid" else names) for c in columns] for r in records]
    widths = [max(len(row[i]) for row in rows) for i in range(len(columns))]
    return [indent + "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
            for row in rows]  # fmt: skip


def _cell(value: Any, names: dict[str, str]) -> str:
    if isinstance(value, list | tuple):
        return (_listed(value, names) or "-") if len(value) <= 2 else str(len(value))
    return _value(value, names)


def _listed(values: list[Any] | tuple[Any, ...], names: dict[str, str]) -> str:
    shown = ", ".join(_value(v, names) for v in values[:MAX_LISTED])
    return shown + (f" ... {len(values) - MAX_LISTED} more" if len(values) > MAX_LISTED else "")


def _value(value: Any, names: dict[str, str]) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, str) and value in names:
        return names[value]
    return str(value)
