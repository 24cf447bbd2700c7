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


# The harness's rooms, bottom first: a room imports only rooms on a lower floor
# (DESIGN.md, "Floors inside harness/"). Rooms on one floor do not import each other.
HARNESS_FLOORS: tuple[tuple[str, ...], ...] = (
    ("vocab",),  # the run's words: events, observer protocols, the write-only sink, the verdict
    ("config",),  # the schema and its loading
    ("engine",),  # the run's processes: physics, render pool, rings, typed messages
    ("record",),  # MCAP and the run folder
    ("analysis",),  # timing observers
    ("cases",),  # the corner-case detector and its casebook
    ("report",),  # pages people read, CI outputs, progress
    ("run",),  # one run: driver, loop, shards, its summary
    ("check", "study", "search"),  # what runs runs: the gate, calibrate, target-check, studies, searches
    ("cli",),  # the commands
)


def _floor(room: str) -> int:
    for k, rooms in enumerate(HARNESS_FLOORS):
        if room in rooms:
            return k
    raise AssertionError(f"harness/{room}/ is on no floor: add it to HARNESS_FLOORS")


def _upward(root: Path) -> list[str]:
    """Every import (inside functions too) from a harness room to a room on its own
    floor or above: ``file:room -> module``."""
    found = []
    for p in sorted((root / "harness").rglob("*.py")):
        parts = p.relative_to(root / "harness").parts
        if len(parts) < 2:
            continue
        here = _floor(parts[0])
        for m in sorted(_imports(p)):
            q = m.split(".")
            if len(q) > 3 and q[:2] == ["hil", "harness"] and q[2] != parts[0] \
                    and (root / "harness" / q[2]).is_dir() and _floor(q[2]) >= here:
                found.append(f"{'/'.join(parts)} -> {'.'.join(q[2:4])}")
    return sorted(set(found))


def test_every_harness_room_is_on_a_floor() -> None:
    rooms = {p.name for p in (ROOT / "harness").iterdir() if (p / "__init__.py").exists()}
    assert rooms == {r for floor in HARNESS_FLOORS for r in floor}


def test_no_harness_room_imports_upward() -> None:
    assert _upward(ROOT) == []


def test_the_floor_check_sees_an_upward_import(tmp_path: Path) -> None:
    """A lazy import from the vocabulary up to the run is caught."""
    for room in ("vocab", "run"):
        (tmp_path / "harness" / room).mkdir(parents=True)
        (tmp_path / "harness" / room / "__init__.py").write_text("")
    (tmp_path / "harness" / "vocab" / "words.py").write_text(
        "def late():\n    from hil.harness.run.driver import execute\n    return execute\n")
    assert _upward(tmp_path) == ["vocab/words.py -> run.driver"]
