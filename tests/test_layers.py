"""The project's packages in layers: each imports only the ones below it.

The library (``ups``) knows none of the others; the daemons (``broker``, ``gateway``) and the
JAUS host stand on the library; the demo and the benchmarks on all of those; the command line
(``upscli``) on everything. Read from the sources (every import, lazy ones included), so a
layer broken in a function that no test runs is caught too.

Inside a package, the modules import each other without a circle: a helper never reaches back
into the module that uses it (what both need goes into a module below both). Every import
counts here, lazy ones and those made for the type checker only included.

The folders ``broker/``, ``gateway/``, ``jaus/``, ``ros2/``, ``ethercat/``, ``examples/`` and
``benchmarks/``
install as ``ups.broker``, ``ups.gateway``, ... (links in ``ups/``), never under a name of their
own: every import names them so.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

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


def module_name(path: Path) -> str:
    """The name ``path`` is imported by: ``ups._node``, ``ups.broker.can_ecb``, ``ups.tools``."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(["ups", *parts] if parts[0] in LINKED else parts)


def module_imports(path: Path, known: set[str]) -> set[str]:
    """The modules among ``known`` that ``path`` imports, relative imports resolved, and
    ``from PACKAGE import MODULE`` as MODULE (a package's own ``__init__`` not implied)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            modules = {f"{base}.{alias.name}" for alias in node.names} & known
            found |= modules
            if len(modules) < len(node.names):  # names the package (its __init__) defines
                found.add(base)
    return (found & known) - {name}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node of ``graph`` (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in sorted(graph.get(node, ())):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def import_graph(package: str) -> dict[str, set[str]]:
    """Each module of ``package`` (its subpackages included) -> the modules of it it imports."""
    files = sources(package)
    known = {module_name(path) for path in files}
    return {module_name(path): module_imports(path, known) for path in files}


@pytest.mark.parametrize("package", list(BELOW))
def test_no_package_has_an_import_circle(package: str) -> None:
    graph = import_graph(package)
    wrong = [
        ", ".join(circle)
        + " import each other: "
        + "; ".join(f"{a} imports {', '.join(sorted(graph[a] & set(circle)))}" for a in circle)
        for circle in circles(graph)
    ]
    assert not wrong


def test_the_circle_check_sees_a_circle() -> None:
    """Two modules that import each other, a third beside them, one that imports itself."""
    graph = {"a": {"b", "c"}, "b": {"a"}, "c": set(), "d": {"d"}}
    assert circles(graph) == [["a", "b"]]


def test_the_circle_check_resolves_relative_imports() -> None:
    """``from . import _canproto as p`` in ups/_canface.py is an import of ups._canproto."""
    graph = import_graph("ups")
    assert {"ups._canproto", "ups._canrx", "ups._face"} <= graph["ups._canface"]
    assert "ups._node" in graph["ups.tools._net"]
