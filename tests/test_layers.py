"""The project's packages in layers: each imports only the ones below it.

The library (``ups``) knows none of the others; the daemons (``broker``, ``gateway``) and the
JAUS host stand on the library; the demo and the benchmarks on all of those; the command line
(``upscli``) on everything. Read from the sources (every import, lazy ones included), so a
layer broken in a function that no test runs is caught too.

The folders ``broker/``, ``gateway/``, ``jaus/``, ``ros2/``, ``ethercat/``, ``examples/`` and
``benchmarks/``
install as ``ups.broker``, ``ups.gateway``, ... (links in ``ups/``), never under a name of their
own: every import names them so.
"""

from __future__ import annotations

import ast
from pathlib import Path

from .procs import ROOT

BELOW: dict[str, set[str]] = {
    "ups": set(),
    "broker": {"ups"},
    "gateway": {"ups", "broker"},
    "jaus": {"ups"},
    "ros2": {"ups"},
    "ethercat": {"ups"},
    "examples": {"ups", "broker", "gateway", "jaus", "ros2", "ethercat"},
    "benchmarks": {"ups", "broker", "gateway", "jaus", "ros2", "ethercat"},
    "upscli": {"ups", "broker", "gateway", "jaus", "ros2", "ethercat", "examples", "benchmarks"},
}


#: installed as ups.<name>
LINKED = ("broker", "gateway", "jaus", "ros2", "ethercat", "examples", "benchmarks")
SOURCES = (*BELOW, "tests")


def sources(package: str) -> list[Path]:
    """The Python files of the folder ``package`` (for ``ups``, not those behind its links)."""
    files = sorted((ROOT / package).rglob("*.py"))
    return [f for f in files if not (package == "ups" and f.relative_to(ROOT).parts[1] in LINKED)]


def imports(path: Path) -> list[str]:
    """Every module ``path`` imports absolutely, ``from ups import broker`` as ``ups.broker``."""
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
            if node.module == "ups":
                names += [f"ups.{a.name}" for a in node.names if a.name in LINKED]
    return names


def layer_of(name: str) -> str:
    parts = name.split(".")
    return parts[1] if parts[0] == "ups" and len(parts) > 1 and parts[1] in LINKED else parts[0]


def imported_packages(package: str) -> dict[str, set[str]]:
    """The project's packages that ``package`` imports (absolute imports), each with the files
    that import it."""
    found: dict[str, set[str]] = {}
    for path in sources(package):
        for name in imports(path):
            top = layer_of(name)
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


def test_the_linked_folders_are_imported_by_their_installed_names_only() -> None:
    """``import broker`` works in a checkout, but not once installed: nobody may write it."""
    wrong = {
        f"{path.relative_to(ROOT)} imports {name}"
        for package in SOURCES
        for path in sources(package)
        for name in imports(path)
        if name.split(".")[0] in LINKED
    }
    assert not wrong
    for name in LINKED:
        assert (ROOT / "ups" / name).resolve() == ROOT / name, f"ups/{name} links to ../{name}"
