"""Campaign progress: a live rich bar on a terminal (episodes, virtual km, corner
cases, throughput), one line per episode elsewhere (CI logs, a Kubernetes pod)."""

from __future__ import annotations

import time

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from hil.harness.search.episode import EpisodeResult, Status
from hil.harness.search.shard import Shard


class CampaignProgress:
    """A ``Reporter`` (hil.harness.search.campaign) for people: ``live`` shows a bar."""

    def __init__(self, console: Console, *, live: bool) -> None:
        self.console = console
        self.live = live and console.is_terminal
        self._bar: Progress | None = None
        self._task: TaskID | None = None
        self.total = self.done = self.ran = self.cases = 0
        self.km = 0.0
        self._t0 = time.perf_counter()

    def start(self, *, total: int, done: int, workers: int, shard: Shard, km: float = 0.0, cases: int = 0) -> None:
        self.total, self.done, self.km, self.cases = total, done, km, cases  # a resumed campaign's so far
        self._t0 = time.perf_counter()
        where = "" if shard.count == 1 else f" (shard {shard})"
        self.console.print(f"{total} episodes{where}, {done} done already, {workers} worker"
                           f"{'s' if workers != 1 else ''}")
        if self.live:
            self._bar = Progress(TextColumn("[bold]episodes"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("{task.fields[km]:.3f} km · {task.fields[cases]} cases · "
                                            "{task.fields[rate]:.1f} ep/min"),
                                 TimeElapsedColumn(), TimeRemainingColumn(), console=self.console)
            self._bar.start()
            self._task = self._bar.add_task("search", total=total, completed=done, km=km, cases=cases, rate=0.0)

    def _rate(self) -> float:
        dt = time.perf_counter() - self._t0
        return self.ran / dt * 60 if dt > 0 else 0.0

    def episode(self, r: EpisodeResult) -> None:
        self.done += 1
        self.ran += 1
        self.km += r.virtual_km
        self.cases += len(r.cases)
        if self._bar is not None and self._task is not None:
            self._bar.update(self._task, completed=self.done, km=self.km, cases=self.cases, rate=self._rate())
            if r.status != Status.OK:
                self._bar.console.print(f"[yellow]e{r.index:05d} {r.status}: {r.error or r.ended_by}[/yellow]")
            return
        what = (f"{r.sim_s:.1f} s sim in {r.wall_s:.1f} s, {r.virtual_km:.3f} km, {len(r.cases)} cases, "
                f"score {r.score:g}") if r.status != Status.ERROR else r.error
        self.console.print(f"e{r.index:05d} {r.status:5s} {what}  [{self.done}/{self.total}, {self.km:.3f} km, "
                           f"{self.cases} cases, {self._rate():.1f} ep/min]", highlight=False, markup=False)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None
