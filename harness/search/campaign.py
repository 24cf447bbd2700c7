"""Running a campaign (or one shard of it) with a process pool or a Dask cluster.

``run_campaign`` runs the episodes of its shard that the campaign folder does not
hold yet, ``workers`` at a time, each in a pool process of its own (``spawn``: a
fresh interpreter, its own simulator, renderer and target), or as tasks on a Dask
cluster (``engine=DaskEngine(...)``, engine.py): the same draws either way. A random campaign
streams its episodes through the pool; a guided one runs generation by generation,
each drawn from the results of the earlier ones in this folder (see sampling.py),
so with ``--shard`` every shard runs its own guided search on its own slice, while
generation 0 — and a whole random campaign — is the same episode for episode
however it is sharded.

Results go to ``campaign.sqlite`` as each episode ends, so a stopped campaign keeps
what it ran and ``resume`` continues it (an episode folder without a finished row is
an interrupted attempt: it is removed and run again). SIGTERM or Ctrl-C stop
submitting; episodes already running finish (a Ctrl-C reaches them too and ends them
early, recorded as ``early``). Then ``summary.json`` and ``report.html`` are written.
"""

from __future__ import annotations

import shutil
import signal
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from hil.harness.search.db import DB_NAME, CampaignDB, now_text
from hil.harness.search.executor import ProcessEngine
from hil.harness.search.episode import EpisodeResult, Status, episode_dirname
from hil.harness.search.sampling import (
                                         Draw,
                                         Past,
                                         draw_generation,
                                         generation_of,
                                         is_guided,
                                         )
from hil.common.errors import ConfigError
from hil.harness.search.shard import Shard
from hil.harness.search.spec import Campaign


class Reporter(Protocol):
    """Where progress goes (a live bar, log lines, or nothing)."""

    def start(self, *, total: int, done: int, workers: int, shard: Shard, km: float = 0.0, cases: int = 0) -> None:
        """``done`` episodes of ``total`` ran before (a resumed campaign), with ``km``
        virtual kilometres and ``cases`` corner cases between them."""

    def episode(self, r: EpisodeResult) -> None: ...

    def close(self) -> None: ...


class QuietReporter:
    def start(self, *, total: int, done: int, workers: int, shard: Shard, km: float = 0.0, cases: int = 0) -> None:
        pass

    def episode(self, r: EpisodeResult) -> None:
        pass

    def close(self) -> None:
        pass


@dataclass
class Outcome:
    """What ``run_campaign`` did: the episodes of its shard (``planned``), those this
    call ran, whether it was stopped, and the campaign summary written after."""

    out_dir: Path
    shard: Shard
    planned: int
    ran: list[EpisodeResult] = field(default_factory=list)
    already_done: int = 0
    stopped: bool = False
    wall_s: float = 0.0
    summary: dict[str, Any] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        """Every episode of the shard ran to its duration."""
        ok = sum(1 for r in self.ran if r.status == Status.OK)
        return not self.stopped and ok + self.already_done == self.planned


def check_campaign_dir(out: Path, *, resume: bool) -> None:
    """Whether ``out`` may take this campaign (``prepare_campaign_dir``'s refusals,
    before anything is written or printed).

    Raises:
        ConfigError: ``out`` holds a campaign and ``resume`` is off, or is a file or
            a non-empty folder that is not a campaign.
    """
    if out.exists():
        if not out.is_dir():
            raise ConfigError(f"--out {out}: is a file; choose a folder")
        if (out / DB_NAME).exists():
            if not resume:
                raise ConfigError(f"--out {out}: holds a campaign already ({DB_NAME}); add --resume to continue "
                                  "it, or choose another folder")
        elif any(out.iterdir()):
            raise ConfigError(f"--out {out}: a folder that is not empty and holds no campaign; choose another")


def prepare_campaign_dir(out: Path, *, resume: bool) -> None:
    """Create ``out`` or accept it for ``resume``; never write over anything else.

    Raises:
        ConfigError: ``check_campaign_dir``'s refusals, or ``out`` cannot be written.
    """
    check_campaign_dir(out, resume=resume)
    try:
        (out / "episodes").mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"--out {out}: cannot write there: {err.strerror or err}") from err


def run_campaign(c: Campaign, *, out: Path, gl_backend: str, shard: Shard | None = None, workers: int = 1,
                 resume: bool = False, reporter: Reporter | None = None,
                 install_signal_handlers: bool = True, engine: Engine | None = None) -> Outcome:
    """Run the campaign's episodes of ``shard`` into ``out`` (see the module docstring).

    ``engine`` (a ``DaskEngine``; default a process pool of ``workers``) runs the
    episodes; one passed in is left open (its owner closes it), and its own worker
    count replaces ``workers``.

    Raises:
        ConfigError: a bad ``out`` (see ``prepare_campaign_dir``), ``workers`` < 1, or
            ``resume`` of a folder holding another campaign, or another shard (unless
            ``shard`` is the whole campaign, which runs whatever is missing, e.g. from
            a merge of the slices that finished).
    """
    if workers < 1:
        raise ConfigError(f"--workers {workers}: expected at least 1")
    own_engine = engine is None
    engine = engine or ProcessEngine(workers=workers, gl_backend=gl_backend)
    workers = engine.workers
    shard = shard or Shard()
    prepare_campaign_dir(out, resume=resume)
    reporter = reporter or QuietReporter()
    with CampaignDB(out / DB_NAME) as db:
        db.init_campaign(c)
        others = {s["shard"] for s in db.shards()} - {str(shard)}
        if others and shard.count > 1:  # the whole campaign (0/1) may finish a merge's missing episodes
            raise ConfigError(f"--out {out}: holds shard {', '.join(sorted(others))} of this campaign, not "
                              f"{shard}; resume with the same --shard")
        known = db.episodes()
        done = {e["episode"] for e in known if e["status"] == Status.OK}
        history = [Past(e["episode"], tuple(e["unit"]), float(e["score"] or 0.0))
                   for e in known if e["status"] == Status.OK]
        mine = [i for i in range(c.episodes) if shard.owns(i)]
        todo = [i for i in mine if i not in done]
        shard_row = db.add_shard(str(shard), str(out), started=now_text())
        oc = Outcome(out_dir=out, shard=shard, planned=len(mine), already_done=len(mine) - len(todo))
        stop = _StopFlag()
        restore = stop.install() if install_signal_handlers else None
        before = [e for e in known if e["episode"] in done and shard.owns(e["episode"])]
        reporter.start(total=len(mine), done=oc.already_done, workers=workers, shard=shard,
                       km=sum(float(e["virtual_km"] or 0.0) for e in before),
                       cases=sum(int(e["cases"] or 0) for e in before))
        t0 = time.perf_counter()
        pool = _Pool(engine)
        try:
            def on_result(r: EpisodeResult) -> None:
                db.put_episode(r)
                oc.ran.append(r)
                if r.status == Status.OK:
                    history.append(Past(r.index, tuple(r.unit), r.score))
                reporter.episode(r)

            for batch in _batches(c, todo, history):
                pool.run(batch(), c, out=out, shard=str(shard), on_result=on_result, stop=stop)
                if stop.set:
                    break
        finally:
            if own_engine:
                engine.close()
            reporter.close()
            if restore is not None:
                restore()
        oc.stopped = stop.set
        oc.wall_s = round(time.perf_counter() - t0, 3)
        db.finish_shard(shard_row, wall_s=oc.wall_s, episodes=len(oc.ran))
    from hil.harness.search.campaign_page import write_outputs

    oc.summary = write_outputs(out)
    return oc


def _batches(c: Campaign, todo: list[int], history: list[Past]) -> Iterator[Callable[[], Iterator[Draw]]]:
    """Batches of draws, each produced when its turn comes: one streaming batch for
    a random campaign; one per generation (drawn from the history so far) for a
    guided one."""
    wanted = set(todo)
    gens = sorted({generation_of(c, i) for i in todo})
    if not is_guided(c):
        def all_draws() -> Iterator[Draw]:
            for g in gens:
                yield from (d for d in draw_generation(c, g) if d.index in wanted)
        yield all_draws
        return
    for g in gens:
        def one(g: int = g) -> Iterator[Draw]:
            return iter([d for d in draw_generation(c, g, history) if d.index in wanted])
        yield one


class _StopFlag:
    def __init__(self) -> None:
        self.set = False

    def install(self) -> Callable[[], None]:
        def on_signal(_signum: int, _frame: object) -> None:
            self.set = True

        prev = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}

        def restore() -> None:
            for s, h in prev.items():
                signal.signal(s, h)

        return restore


class Engine(Protocol):
    """Runs episodes (engine.py: ``ProcessEngine``, ``DaskEngine``)."""

    workers: int

    def submit(self, c: Campaign, d: Draw, *, out: Path, shard: str) -> Future[EpisodeResult]: ...

    def reset(self) -> None: ...

    def close(self) -> None: ...


class _Pool:
    """Feeds an engine at most ``2 x workers`` episodes at once; a process pool that
    breaks (a worker killed) is replaced and its episodes recorded as errors."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.workers = engine.workers

    def run(self, draws: Iterator[Draw], c: Campaign, *, out: Path, shard: str,
            on_result: Callable[[EpisodeResult], None], stop: _StopFlag) -> None:
        running: dict[Future[EpisodeResult], Draw] = {}
        exhausted = False
        while True:
            while not exhausted and not stop.set and len(running) < 2 * self.workers:
                d = next(draws, None)
                if d is None:
                    exhausted = True
                    break
                stale = out / "episodes" / episode_dirname(d.index)
                if stale.exists():  # an interrupted attempt: its row never said ok
                    shutil.rmtree(stale)
                running[self.engine.submit(c, d, out=out, shard=shard)] = d
            if stop.set:  # episodes not started yet are dropped; running ones finish
                for fut in [f for f in running if f.cancel()]:
                    del running[fut]
            if not running:
                return
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                d = running.pop(fut)
                try:
                    r = fut.result()
                except BrokenProcessPool as err:
                    r = _failed(d, shard, f"worker process died ({err})")
                    self.engine.reset()
                except Exception as err:  # noqa: BLE001 - recorded; the campaign goes on
                    r = _failed(d, shard, f"{type(err).__name__}: {err}")
                on_result(r)


def _failed(d: Draw, shard: str, error: str) -> EpisodeResult:
    return EpisodeResult(index=d.index, shard=shard, generation=d.generation, origin=d.origin, seed=d.seed,
                         params=dict(d.values), unit=list(d.unit), status=Status.ERROR,
                         dir=f"episodes/{episode_dirname(d.index)}", error=error)


__all__ = ["Engine", "Outcome", "QuietReporter", "Reporter", "check_campaign_dir", "prepare_campaign_dir",
           "run_campaign"]
