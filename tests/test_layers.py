"""The project's packages in layers: each imports only the ones below it.

The library (``ups``) knows none of the others; the daemons (``broker``, ``gateway``) and the
JAUS host stand on the library; the demo and the benchmarks on all of those; the command line
(``upscli``) on everything. Read from the sources (every import, lazy ones included), so a
layer broken in a function that no test runs is caught too.
"""

from __future__ import annotations

import ast

from .procs import ROOT

BELOW: dict[str, set[str]] = {
    "ups": set(),
    "broker": {"ups"},
    "gateway": {"ups", "broker"},
    "jaus": {"ups"},
    "examples": {"ups", "broker", "gateway", "jaus"},
    "benchmarks": {"ups", "broker", "gateway", "jaus"},
    "upscli": {"ups", "broker", "gateway", "jaus", "examples", "benchmarks"},
}


def imported_packages(package: str) -> dict[str, set[str]]:
    """The project's packages that ``package`` imports (absolute imports), each with the files
    that import it."""
    found: dict[str, set[str]] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top in BELOW and top != package:
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def test_every_package_imports_only_the_layers_below_it() -> None:
    wrong = {
        f"{package} imports {other} (in {', '.join(sorted(files))})"
        for package, below in BELOW.items()
        for other, files in imported_packages(package).items()
        if other not in below
    }
    assert not wrong


def test_the_check_sees_lazy_imports() -> None:
    """upscli imports broker only inside functions: the check must see those imports."""
    assert "broker" in imported_packages("upscli")
