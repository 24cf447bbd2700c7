"""The transport table (adapters.transports) and the import graph it keeps acyclic."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from adapters import transports
from adapters.link import TRANSPORTS, Link, open_link
from adapters.transports import BACKENDS, NAMES, Transport
from hil_errors import TransportError

ROOT = Path(__file__).resolve().parents[2]


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


@pytest.mark.parametrize("package", ["adapters", "timing", "hil_errors"])
def test_no_import_circles(package: str) -> None:
    assert _cycles(_graph(package)) == []


def test_the_table_imports_no_transport_and_the_error_tree_imports_nothing_of_ours() -> None:
    ours = ("adapters", "timing", "scenarios", "harness", "targets", "hil_errors")
    table = {i for i in _imports(ROOT / "adapters" / "transports.py") if i.split(".")[0] in ours}
    assert table <= {"hil_errors", "hil_errors.TransportError"}
    errors = {i for i in _imports(ROOT / "hil_errors" / "__init__.py") if i.split(".")[0] in ours}
    assert errors == set()


def test_every_transport_has_a_row_and_its_halves_resolve() -> None:
    assert set(BACKENDS) == set(Transport) and NAMES == TRANSPORTS == ("local", "zenoh", "can", "mixed", "tcp")
    for kind in Transport:
        cls = transports.link_class(kind)
        assert issubclass(cls, Link) and cls.transport_name == kind.value
        assert callable(transports.serve_function(kind.value))
    assert {t for t, b in BACKENDS.items() if b.shared is not None} == {Transport.LOCAL, Transport.ZENOH}
    assert callable(transports.shared_serve_function("zenoh"))
    with pytest.raises(TransportError, match="a shared target serves over local or zenoh, not 'can'"):
        transports.shared_serve_function(Transport.CAN)


def test_the_config_takes_the_same_enum() -> None:
    from harness.config import Transport as ConfigTransport
    from harness.config import parse_config

    assert ConfigTransport is Transport
    assert parse_config({"target": {"transport": "tcp", "command": ["x"]}}).target.transport is Transport.TCP


def test_unknown_transport_is_one_error_listing_the_valid_ones() -> None:
    with pytest.raises(TransportError, match=r"unknown transport 'pigeon'; valid: local, zenoh, can, mixed, tcp"):
        open_link("pigeon")
    from adapters.sdk import serve

    with pytest.raises(TransportError, match="unknown transport 'pigeon'"):
        serve(lambda frame: None, target_name="t", transport="pigeon")  # type: ignore[arg-type,return-value]
