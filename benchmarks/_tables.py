"""A benchmark's results as tables (``Table``) and the aligned text the terminal shows them as:
below both the measuring modules and ``_report.py``, which gathers their tables into
``report.md`` (so that none of them imports the report that imports it)."""

from __future__ import annotations

Table = tuple[str, list[str], list[list[str]]]  # title, header, rows


def aligned(tables: list[Table]) -> list[str]:
    """Each table as the terminal shows it: its title, its columns aligned, a blank line."""
    lines = []
    for title, head, rows in tables:
        every = [head, *rows]
        widths = [max(len(row[i]) for row in every) for i in range(len(head))]
        lines.append(title)
        lines += ["  " + "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip()
                  for row in every]  # fmt: skip
        lines.append("")
    return lines
