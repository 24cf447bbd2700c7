"""The import graph: no circles inside a package, and the never-arrows of DESIGN.md
(``timing`` imports only ``hil_errors``; ``scenarios`` and ``adapters`` never import
``harness``; ``targets`` never imports ``harness`` or ``scenarios``). Imports inside
functions count (a lazy import is still an arrow); ``if TYPE_CHECKING:`` ones do not."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil_errors", "timing", "scenarios", "adapters", "targets", "harness")


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at any depth (functions included), except under
    ``if TYPE_CHECKING:``; ``from a import b`` counts as ``a`` and ``a.b``."""
    out: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                for stmt in child.orelse:
                    visit(stmt)
                continue
            if isinstance(child, ast.Import):
                out.update(a.name for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                out.add(child.module)
                out.update(f"{child.module}.{a.name}" for a in child.names)
            visit(child)

    visit(ast.parse(path.read_text(encoding="utf-8")))
    return out


def _graph(package: str) -> dict[str, set[str]]:
    files = {".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p
             for p in sorted((ROOT / package).rglob("*.py"))}
    return {m: {i for i in _imports(p) if i in files and i != m} for m, p in files.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def test_cycle_finder_finds_a_cycle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("package", ["hil_errors", "timing", "scenarios", "adapters", "targets"])
def test_no_import_circles(package: str) -> None:
    assert _cycles(_graph(package)) == []


def test_the_table_imports_no_transport_and_the_error_tree_imports_nothing_of_ours() -> None:
    ours = ("adapters", "timing", "scenarios", "harness", "targets", "hil_errors")
    table = {i for i in _imports(ROOT / "adapters" / "transports.py") if i.split(".")[0] in ours}
    assert table <= {"hil_errors", "hil_errors.TransportError"}
    errors = {i for i in _imports(ROOT / "hil_errors" / "__init__.py") if i.split(".")[0] in ours}
    assert errors == set()


@pytest.mark.parametrize("package, allowed", [
    ("hil_errors", set()),
    ("timing", {"hil_errors"}),
    ("scenarios", {"hil_errors", "timing"}),
    ("adapters", {"hil_errors", "timing"}),
    ("targets", {"hil_errors", "timing", "adapters"}),
])
def test_never_arrows(package: str, allowed: set[str]) -> None:
    crossing = {}
    for p in sorted((ROOT / package).rglob("*.py")):
        tops = {i.split(".")[0] for i in _imports(p)} & set(PACKAGES)
        if tops - allowed - {package}:
            crossing[str(p.relative_to(ROOT))] = sorted(tops - allowed - {package})
    assert crossing == {}
