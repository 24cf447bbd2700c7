"""The live progress display (rich) and the end-of-run table; ``WorkProgress`` for
other long work (``hil study``, ``hil compare``), with the time left."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rich import box
from rich.console import Console
from rich.live import Live
from rich.table import Table

from hil.common.eta import time_left
from hil.harness.run.vehicle_state import ProgressRow


def make_console() -> Console:
    """A console; when output is not a terminal (CI logs, pipes) tables get room."""
    console = Console()
    if not console.is_terminal:
        console.width = max(console.width, 120)
    return console


def _table(title: str, headers: tuple[str, ...]) -> Table:
    """A right-aligned table narrow enough for 80 columns: each header's words are
    stacked (``e2e`` / ``p99`` / ``ms``) so no header is cut to ``e2e…``."""
    t = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD, padding=0, show_edge=False)
    for col in headers:
        t.add_column("\n".join(col.split()), justify="right", no_wrap=True)
    return t


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


def final_table(summary: dict[str, Any]) -> Table:
    rt = summary["realtime"]
    title = (f"{summary['name']}: {summary['sim_time_s']:.2f} s simulated in {summary['wall_time_s']:.2f} s "
             f"({rt['mode']}, real-time factor {rt['achieved_factor']:.2f}, late steps {rt['late_steps']})")
    t = _table(title, ("vehicle", "frames", "applied", "dropped", "fps", "e2e p50 ms", "e2e p99 ms",
                       "e2e max ms", "min gap m", "collisions"))
    for name, v in summary["vehicles"].items():
        e2e = v["latency_ms"]["end_to_end"]
        gap = v["outcome"]["min_gap_m"]
        t.add_row(name, str(v["frames_sent"]), str(v["estimates_applied"]), str(v["dropped"]),
                  f"{v['frames_per_s']:.1f}", _ms(e2e.get("p50_ms")), _ms(e2e.get("p99_ms")),
                  _ms(e2e.get("max_ms")), "-" if gap is None else f"{gap:.2f}",
                  str(v["outcome"]["collisions"]))
    return t


class WorkProgress:
    """Long work in weighted steps (``total``), with the time left at the pace so
    far: a transient rich bar on a terminal (as ``hil search``'s), else, with
    ``lines``, one line per step (CI logs): ``study: 2 of 8 points done (0:41),
    about 3.2 min left``. ``clock`` gives seconds (a test may pass its own)."""

    def __init__(self, console: Console, *, what: str, total: float, unit: str = "steps", lines: bool = True,
                 live: bool = True, clock: Callable[[], float] | None = None) -> None:
        import time

        self.console, self.what, self.total, self.unit = console, what, float(total), unit
        self.lines = lines
        self.live = live and console.is_terminal
        self._clock = clock or time.monotonic
        self._t0 = self._clock()
        self.done = 0.0
        self._bar: Any = None
        self._task: Any = None

    def __enter__(self) -> WorkProgress:
        if self.live:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self._bar = Progress(TextColumn(f"[bold]{self.what}"), BarColumn(), TextColumn("{task.description}"),
                                 TimeElapsedColumn(), TimeRemainingColumn(), console=self.console, transient=True)
            self._bar.start()
            self._task = self._bar.add_task("", total=self.total)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None

    @property
    def elapsed_s(self) -> float:
        return self._clock() - self._t0

    def left(self) -> str:
        return time_left(self.done, self.total, self.elapsed_s)

    def advance(self, amount: float = 1.0, *, note: str = "") -> None:
        """``amount`` more of ``total`` done; ``note`` says what (shown beside)."""
        self.done = min(self.total, self.done + amount)
        if self._bar is not None:
            self._bar.update(self._task, completed=self.done, description=note)
        elif self.lines:
            e = int(self.elapsed_s)
            self.console.print(f"{self.what}: {self.done:g} of {self.total:g} {self.unit} done ({e // 60}:{e % 60:02d})"
                               f", {self.left()}" + (f": {note}" if note else ""), highlight=False, markup=False)
