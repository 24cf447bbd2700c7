"""HTML tables and numbers of the reports (the run's and the study's)."""

from __future__ import annotations

from html import escape
from typing import Any


def ms(v: Any, digits: int = 3) -> str:
    """A number with ``digits`` decimals; ``–`` for what is not a number."""
    return "–" if not isinstance(v, (int, float)) or isinstance(v, bool) else f"{v:.{digits}f}"


def kv_table(rows: list[tuple[str, str]]) -> str:
    """A two-column table: the names (escaped here), the values (HTML as given)."""
    return "<table>" + "".join(f"<tr><th>{escape(k)}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def table(head: list[str], rows: list[list[str]], numeric_from: int = 1) -> str:
    """A table of ``rows`` (HTML cells as given) under ``head`` (escaped here); the
    columns from ``numeric_from`` on are right-aligned numbers."""
    h = "".join(f"<th>{escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f'<td{" class=n" if i >= numeric_from else ""}>{c}</td>'
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


__all__ = ["kv_table", "ms", "table"]
