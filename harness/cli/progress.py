"""The run's live progress display (rich) and its end-of-run table."""

from __future__ import annotations

from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from hil.harness.report.progress import table as _table
from hil.harness.run.vehicle_state import ProgressRow


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


class Progress:
    """Shows sim time, and per vehicle frames/s and end-to-end p50/p99, refreshed at
    most every ``refresh_s`` of wall time. Quiet when disabled or not a terminal."""

    def __init__(self, *, console: Console, enabled: bool, refresh_s: float = 0.25) -> None:
        self.console = console
        self.enabled = enabled and console.is_terminal
        self.refresh_ns = int(refresh_s * 1e9)
        self._live: Live | None = None
        self._last_ns = 0

    def __enter__(self) -> Progress:
        if self.enabled:
            self._live = Live(console=self.console, auto_refresh=False, transient=True)
            self._live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.__exit__(None, None, None)
            self._live = None

    def update(self, *, now_ns: int, sim_time_s: float, duration_s: float, rows: list[ProgressRow]) -> None:
        if self._live is None or now_ns - self._last_ns < self.refresh_ns:
            return
        self._last_ns = now_ns
        t = _table(f"sim {sim_time_s:6.2f} / {duration_s:g} s",
                   ("vehicle", "frames", "fps", "e2e p50 ms", "e2e p99 ms", "dropped", "anomalies"))
        for r in rows:
            t.add_row(r.name, str(r.frames), f"{r.fps:.1f}", _ms(r.e2e_p50_ms), _ms(r.e2e_p99_ms), str(r.dropped),
                      "-" if r.anomalies is None else str(r.anomalies))
        self._live.update(t, refresh=True)


def final_table(summary: dict[str, Any]) -> Group:
    """The run's line (its name, simulated and wall time, real time) over the table of
    its vehicles. (The line as the table's title was wrapped to the table's width,
    padded with spaces.)"""
    rt = summary["realtime"]
    title = (f"{summary['name']}: {summary['sim_time_s']:.2f} s simulated in {summary['wall_time_s']:.2f} s "
             f"({rt['mode']}, real-time factor {rt['achieved_factor']:.2f}, late steps {rt['late_steps']})")
    t = _table(None, ("vehicle", "frames", "applied", "dropped", "fps", "e2e p50 ms", "e2e p99 ms",
                      "e2e max ms", "min gap m", "collisions"))
    for name, v in summary["vehicles"].items():
        e2e = v["latency_ms"]["end_to_end"]
        gap = v["outcome"]["min_gap_m"]
        t.add_row(name, str(v["frames_sent"]), str(v["estimates_applied"]), str(v["dropped"]),
                  f"{v['frames_per_s']:.1f}", _ms(e2e.get("p50_ms")), _ms(e2e.get("p99_ms")),
                  _ms(e2e.get("max_ms")), "-" if gap is None else f"{gap:.2f}",
                  str(v["outcome"]["collisions"]))
    return Group(Text(title, style="table.title"), t)
