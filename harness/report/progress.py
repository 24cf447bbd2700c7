"""Progress people watch: a console that gives CI logs room, the narrow tables of the
run's display (``table``), and ``WorkProgress`` for long work (``hil study``,
``hil compare``, ``hil search``), with the time left. The run's own live display
and end-of-run table are the CLI's (``hil.harness.cli.progress``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rich import box
from rich.console import Console
from rich.table import Table

from hil.common.eta import time_left


def make_console() -> Console:
    """A console; when output is not a terminal (CI logs, pipes) tables get room."""
    console = Console()
    if not console.is_terminal:
        console.width = max(console.width, 120)
    return console


def table(title: str | None, headers: tuple[str, ...]) -> Table:
    """A right-aligned table narrow enough for 80 columns: each header's words are
    stacked (``e2e`` / ``p99`` / ``ms``) so no header is cut to ``e2e…``."""
    t = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD, padding=0, show_edge=False)
    for col in headers:
        t.add_column("\n".join(col.split()), justify="right", no_wrap=True)
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
