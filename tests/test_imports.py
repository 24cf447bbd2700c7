"""The import graph: no circles inside a package, the never-arrows of DESIGN.md
(``timing`` imports only ``common``, the leaf; ``scenarios`` and ``adapters`` never
import ``harness``; ``targets`` never imports ``harness`` or ``scenarios``), and every
import of ours through the ``hil`` namespace. Imports inside functions count (a lazy
import is still an arrow); ``if TYPE_CHECKING:`` ones do not."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Folder -> what it installs as: every folder is hil.<folder> (setup.py).
FOLDERS = ("common", "timing", "scenarios", "adapters", "targets", "harness", "training")


def _top(module: str) -> str | None:
    """The folder of ours a module name belongs to (``hil.timing.sync`` -> ``timing``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "hil" and parts[1] in FOLDERS else None


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
    files = {"hil." + ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p
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


@pytest.mark.parametrize("package", FOLDERS)
def test_no_import_circles(package: str) -> None:
    assert _cycles(_graph(package)) == []


def test_the_table_imports_no_transport_and_the_leaf_imports_nothing_of_ours() -> None:
    table = {i for i in _imports(ROOT / "adapters" / "transports.py") if _top(i)}
    assert table <= {"hil.common.errors", "hil.common.errors.TransportError"}
    leaf = {i for p in (ROOT / "common").rglob("*.py") for i in _imports(p) if _top(i) not in (None, "common")}
    assert leaf == set()


@pytest.mark.parametrize("package, allowed", [
    ("common", set()),
    ("timing", {"common"}),
    ("scenarios", {"common", "timing"}),
    ("adapters", {"common", "timing"}),
    ("targets", {"common", "timing", "adapters"}),
    ("training", {"common", "timing", "adapters", "scenarios", "targets"}),
])
def test_never_arrows(package: str, allowed: set[str]) -> None:
    crossing = {}
    for p in sorted((ROOT / package).rglob("*.py")):
        tops = {t for i in _imports(p) if (t := _top(i))}
        if tops - allowed - {package}:
            crossing[str(p.relative_to(ROOT))] = sorted(tops - allowed - {package})
    assert crossing == {}


def test_nothing_of_ours_is_imported_by_a_global_top_level_name() -> None:
    """``import timing`` would work from the repository root and load a second copy of
    the package next to ``hil.timing``: every import of ours names the namespace."""
    bare = {}
    for folder in (*FOLDERS, "tests", "bench", "tools", "sdk"):
        for p in sorted((ROOT / folder).rglob("*.py")):
            found = sorted(i for i in _imports(p) if i.split(".")[0] in (*FOLDERS, "hil_errors"))
            if found:
                bare[str(p.relative_to(ROOT))] = found
    assert bare == {}


def test_harness_modules_live_in_rooms() -> None:
    """harness/ holds rooms (folders), not a flat hall of modules."""
    flat = sorted(p.name for p in (ROOT / "harness").glob("*.py") if p.name != "__init__.py")
    assert flat == []
