"""What ``hil compare`` prints: the table of checks, the line on how they were judged,
each figure over its limit that did not fail and why, and the outcome line.

A check over its limit is never printed ``ok``: it fails (``REGRESSION``), or it is
``over, not significant`` with the reason and the numbers under the table.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.console import JustifyMethod
    from rich.table import Table

    from hil.harness.check.gate import Check, GateSettings
    from hil.harness.check.gate_tolerances import Tolerances


def value(metric: str, v: float | None) -> str:
    """A figure with its unit: ``3.416 ms``, a drop rate ``1.00 %``; ``–`` when none."""
    if v is None:
        return "–"
    return f"{v * 100:.2f} %" if metric == "drop_rate" else f"{v:.3f} ms"


def change(c: Check) -> str:
    """RUN − BASELINE: ``+3.056 ms (+847.8 %)``, ``×18220`` past tenfold; the note when either is missing."""
    if c.baseline is None or c.run is None:
        return c.note
    d = c.run - c.baseline
    if c.metric == "drop_rate":
        return f"{d * 100:+.2f} pp"
    if not c.baseline:
        return f"{d:+.3f} ms"
    ratio = c.run / c.baseline
    rel = f"×{ratio:.0f}" if abs(ratio) >= 10 else f"{(ratio - 1) * 100:+.1f} %"
    return f"{d:+.3f} ms ({rel})"


def interval(c: Check) -> str:
    if c.ci is None:
        return "point" if c.method.value == "point" else "–"
    lo, hi = c.ci
    if c.metric == "drop_rate":
        return f"{lo * 100:+.2f} .. {hi * 100:+.2f} pp"
    return f"{lo:+.3f} .. {hi:+.3f}"


def percent(p: float, decimals: int = 1) -> str:
    """A probability as a person reads it: ``96.4 %``, ``<0.1 %``, ``>99.9 %``."""
    v, edge = p * 100, 10.0 ** -decimals
    return f"<{edge:g} %" if v < edge else f">{100 - edge:g} %" if v > 100 - edge else f"{v:.{decimals}f} %"


def sure(c: Check) -> str:
    return "–" if c.p_worse is None else percent(c.p_worse)


def name_of(c: Check) -> str:
    """``ego0 transport p50``, ``ego0 drop_rate``."""
    return f"{c.vehicle} {c.stage} {c.metric}".replace(" - ", " ")


def row_text(c: Check, *, p_worse: bool = True) -> str:
    """One check on one line, with its numbers: ``ego0 transport p50 0.360 → 3.416 ms,
    +3.056 ms (+847.8 %), limit ≤ 0.860 ms, P(worse) 96.4 %`` (that last without ``p_worse``)."""
    if c.baseline is None or c.run is None:
        return f"{name_of(c)}: {c.note}"
    base = value(c.metric, c.baseline)
    text = f"{name_of(c)} {base.removesuffix(' ms').removesuffix(' %')} → {value(c.metric, c.run)}, {change(c)}"
    if c.limit is not None:
        text += f", limit ≤ {value(c.metric, c.limit)}"
    if p_worse and c.p_worse is not None:
        text += f", P(worse) {sure(c)}"
    return text


def render(checks: Sequence[Check], *, failures_only: bool = False, confidence: float = 0.95) -> Table:
    """A rich table of ``checks``."""
    from rich.table import Table

    style = {"REGRESSION": "bold red", "MISSING": "bold red", "better": "green", "new": "cyan", "no data": "dim",
             "over, not significant": "yellow", "ok": ""}
    t = Table(title="latency regression check (RUN against BASELINE)", title_justify="left")
    columns: tuple[tuple[str, JustifyMethod], ...] = (
        ("vehicle", "left"), ("stage", "left"), ("metric", "left"), ("baseline", "right"), ("run", "right"),
        ("change", "right"), (f"{confidence * 100:g} % interval", "right"), ("limit", "right"), ("P(worse)", "right"),
        ("verdict", "left"))
    for col, just in columns:
        t.add_column(col, justify=just)
    for c in checks:
        if failures_only and not c.verdict.fails:
            continue
        v = c.verdict.value
        t.add_row(c.vehicle, c.stage, c.metric, value(c.metric, c.baseline), value(c.metric, c.run), change(c),
                  interval(c), "–" if c.limit is None else f"≤ {value(c.metric, c.limit)}", sure(c),
                  f"[{style[v]}]{v}[/]" if style.get(v) else v)
    return t


def judged_lines(checks: Sequence[Check], tol: Tolerances, settings: GateSettings) -> list[str]:
    """How the checks judged from samples were judged (two lines; none when no check was)."""
    from hil.harness.check.gate_tolerances import LATENCY_METRICS

    judged = [c for c in checks if c.method.value == "samples"]
    if not judged:
        return []
    need = judged[0].need or 1.0
    noise = ", ".join(f"{m} {tol.noise_of(m).rel * 100:g} % & {tol.noise_of(m).abs:g} ms" for m in LATENCY_METRICS)
    return [f"{len(judged)} checks judged from per-frame samples: each fails only when P(worse) ≥ {need * 100:.2f} % "
            f"(alpha {settings.alpha:g} over {len(judged)} checks)",
            f"run-to-run noise counted: {noise} (own figures for {', '.join(sorted(tol.stage_noise))}); "
            f"{settings.resamples} block-bootstrap resamples, seed {settings.seed}"]


def outcome_lines(checks: Sequence[Check]) -> list[str]:
    """The lines under the table (rich markup): each figure over its limit that did
    not fail, with why; then the outcome, which never says "all within their limits"
    while one is over."""
    over = [c for c in checks if c.reason]
    lines = [f"[yellow]{row_text(c, p_worse=False)}: {c.reason}[/yellow]" for c in over]
    failed = [c for c in checks if c.verdict.fails]
    if failed:
        names = ", ".join(name_of(c) for c in failed[:8])
        lines.append(f"[bold red]REGRESSION[/]: {len(failed)} of {len(checks)} checks failed ({names}"
                     + (", ..." if len(failed) > 8 else "") + ")")
    elif over:
        lines.append(f"[green]ok[/]: no regression: {len(checks) - len(over)} of {len(checks)} checks within "
                     f"their limits, {len(over)} over {'its' if len(over) == 1 else 'their'} limit but not "
                     f"significant ({', '.join(name_of(c) for c in over[:8])})")
    else:
        lines.append(f"[green]ok[/]: all {len(checks)} checks within their limits")
    return lines


__all__ = ["change", "interval", "judged_lines", "name_of", "outcome_lines", "percent", "render", "row_text", "sure",
           "value"]
