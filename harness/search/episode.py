"""One episode: a lockstep run of the campaign's config with its draw, in a worker.

``run_episode`` is what a pool worker executes: it builds the episode's run config,
runs it (``hil.harness.run.driver.execute``) into its own run folder ``CAMPAIGN/episodes/eNNNNN``
(``config.json`` + ``run.mcap`` + ``corner_cases.sqlite``: ``hil replay`` takes it as
it is), then reads back what the campaign keeps: the outcome, the corner cases, the
distance every ego drove (virtual km, from ``/ground_truth``) and a hash of the
ground-truth trace (same seed and values give the same hash).

A worker process chooses the GL backend before anything imports MuJoCo
(``init_worker``) and ignores SIGINT while idle; during an episode ``execute``'s own
handlers end the run cleanly (the episode is then ``early``). A failing episode is
recorded with its error; it never takes the campaign down.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hil.common.errors import ConfigError, HilError
from hil.harness.search.sampling import Draw, score
from hil.harness.search.spec import Campaign
from hil.harness.vocab.figures import RunFigures

ERROR_FILE = "episode-error.txt"


class Status:
    """Episode statuses as stored (``ok``: ran its duration; ``early``: stopped
    before it; ``error``: could not run)."""

    OK = "ok"
    EARLY = "early"
    ERROR = "error"


@dataclass
class EpisodeResult:
    """What the campaign keeps of one episode (a row of ``episodes``, plus its cases)."""

    index: int
    shard: str
    generation: int
    origin: str
    seed: int
    params: dict[str, float]
    unit: list[float]
    status: str
    dir: str                      # relative to the campaign folder
    ended_by: str = ""
    error: str = ""
    sim_s: float = 0.0
    wall_s: float = 0.0
    virtual_km: float = 0.0
    anomalies: int = 0
    mismatches: dict[str, int] = field(default_factory=dict)
    collisions: int = 0
    min_gap_m: float | None = None
    score: float = 0.0
    trace_hash: str = ""
    cases: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def episode_dirname(index: int) -> str:
    return f"e{index:05d}"


def init_worker(gl_backend: str) -> None:
    """Pool initializer: fix the GL backend before MuJoCo loads; idle workers leave
    Ctrl-C to the parent (a running episode installs its own handlers)."""
    os.environ["MUJOCO_GL"] = gl_backend
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_episode(campaign: Campaign, draw: Draw, *, campaign_dir: Path, shard: str, gl_backend: str,
                install_signal_handlers: bool = True) -> EpisodeResult:
    """Run one episode into ``campaign_dir/episodes/eNNNNN`` and return its result
    (never raises for a failed episode: its status says ``error``)."""
    from hil.harness.run.driver import execute, prepare_out_dir

    rel = f"episodes/{episode_dirname(draw.index)}"
    out = campaign_dir / rel
    res = EpisodeResult(index=draw.index, shard=shard, generation=draw.generation, origin=draw.origin,
                        seed=draw.seed, params=dict(draw.values), unit=list(draw.unit), status=Status.ERROR,
                        dir=rel)
    t_start = time.perf_counter()
    try:
        cfg = campaign.episode_config(index=draw.index, seed=draw.seed, values=draw.values)
        result = execute(cfg, out_dir=prepare_out_dir(out), gl_backend=gl_backend,
                         install_signal_handlers=install_signal_handlers)
        _fill(res, campaign, RunFigures.from_json(result.summary), out)
    except HilError as err:
        res.error = f"{type(err).__name__}: {err}"
    except Exception as err:  # noqa: BLE001 - one broken episode must not end the campaign
        res.error = f"{type(err).__name__}: {err}"
        try:
            out.mkdir(parents=True, exist_ok=True)
            (out / ERROR_FILE).write_text(traceback.format_exc())
        except OSError:
            pass
    res.wall_s = round(time.perf_counter() - t_start, 4)
    return res


def _fill(res: EpisodeResult, c: Campaign, figures: RunFigures, out: Path) -> None:
    res.ended_by = "" if figures.ended_by is None else figures.ended_by
    res.status = Status.OK if res.ended_by == "duration" else Status.EARLY
    res.sim_s = float(figures.sim_time_s or 0.0)
    mism: dict[str, int] = {}
    gaps: list[float | None] = []
    collided = 0
    for v in figures.vehicles.values():
        res.anomalies += sum(v.anomalies.values())
        for k, n in v.mismatches.items():
            mism[k] = mism.get(k, 0) + n
        gaps.append(None if v.outcome is None else v.outcome.min_gap_m)
        collided += 1 if v.outcome is not None and v.outcome.collisions else 0
    res.mismatches = mism
    res.collisions = collided
    finite = [g for g in gaps if g is not None and math.isfinite(g)]
    res.min_gap_m = round(min(finite), 4) if finite else None
    res.score = score(mismatches=mism, collided_egos=collided, min_gaps_m=gaps, near_miss_m=c.score.near_miss_m)
    km, digest = trace_stats(out / "run.mcap")
    res.virtual_km, res.trace_hash = round(km, 6), digest
    res.cases = _cases(out)


def trace_stats(mcap_path: Path) -> tuple[float, str]:
    """(km driven by all egos, sha256 of the ``/ground_truth`` trace) of a run.

    Distance sums each ego's straight steps between ground-truth records (every
    camera frame): at 20 fps and road speeds the chord error is negligible.

    Raises:
        ConfigError: the file cannot be read.
    """
    from mcap.reader import make_reader

    h = hashlib.sha256()
    last: dict[str, tuple[float, float]] = {}
    egos: set[str] = set()
    dist_m = 0.0
    try:
        with open(mcap_path, "rb") as f:
            for _, _, msg in make_reader(f).iter_messages(topics=["/ground_truth"]):
                h.update(msg.data)
                d = json.loads(msg.data)
                egos.update(e["vehicle"] for e in d.get("egos", ()))
                for e in d.get("entities", ()):
                    name = e["name"]
                    if name not in egos:
                        continue
                    p = (float(e["x_m"]), float(e["y_m"]))
                    if name in last:
                        dist_m += math.hypot(p[0] - last[name][0], p[1] - last[name][1])
                    last[name] = p
    except (OSError, ValueError, KeyError) as err:
        raise ConfigError(f"{mcap_path}: cannot read the ground truth ({err})") from err
    return dist_m / 1000.0, h.hexdigest()


def _cases(out: Path) -> list[dict[str, Any]]:
    from hil.harness.cases.casebook import DB_NAME, read_cases

    if not (out / DB_NAME).is_file():
        return []
    rows, _bad = read_cases(out)
    keep = ("id", "vehicle", "sim_time_ns", "kind", "cause", "severity", "summary", "event", "mcap_path")
    return [{k: r.get(k) for k in keep} for r in rows]


__all__ = ["EpisodeResult", "Status", "episode_dirname", "init_worker", "run_episode", "trace_stats"]
