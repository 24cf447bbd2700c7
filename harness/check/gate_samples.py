"""Per-frame samples of a run for ``hil compare``: every stage's duration of every
frame, and each frame's drop indicator, read back from ``run.mcap``
(``/<vehicle>/pipeline``), in frame order.

The same frames as ``summary.json``'s figures: stage values of the frames whose
estimate was applied (``ok``) and whose timestamps are sane (``hil.timing.anomaly.is_sane``);
a frame is dropped when its record says ``dropped``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.common.errors import ConfigError
from hil.harness.record.run_folder import MCAP_NAME, SUMMARY_NAME, load_summary, pipeline_record, run_dir_of
from hil.timing.anomaly import is_sane
from hil.timing.records import FrameStatus, PipelineRecord

_ACCOUNTED = (FrameStatus.OK, FrameStatus.DROPPED, FrameStatus.STALE)


@dataclass(frozen=True)
class VehicleSamples:
    """One vehicle's samples: ``stages_ms`` per stage name (frame order, ms) and
    ``dropped`` (1.0 per dropped frame, 0.0 per other accounted frame)."""

    stages_ms: dict[str, np.ndarray]
    dropped: np.ndarray


@dataclass(frozen=True)
class RunSamples:
    """Per vehicle samples, plus ``note`` (why there are none, when empty)."""

    vehicles: dict[str, VehicleSamples]
    note: str = ""


def read_samples(run_dir: Path, vehicles: list[str]) -> RunSamples:
    """The samples of ``vehicles`` from ``run_dir/run.mcap``. Never raises: a missing
    or unreadable recording gives no vehicles and a ``note`` saying why."""
    from hil.harness.record.recorder import iter_salvaged_messages

    path = run_dir / MCAP_NAME
    if not path.is_file():
        return RunSamples({}, f"no {MCAP_NAME}")
    topics = {f"/{v}/pipeline": v for v in vehicles}
    recs: dict[str, dict[int, PipelineRecord]] = {v: {} for v in vehicles}
    try:
        for _schema, channel, msg in iter_salvaged_messages(path):
            v = topics.get(channel.topic)
            if v is None:
                continue
            try:
                rec = pipeline_record(json.loads(msg.data))
            except ValueError:
                continue
            if rec is not None:
                recs[v][rec.frame_id] = rec
    except (ConfigError, OSError, ValueError) as err:
        return RunSamples({}, f"{MCAP_NAME} unreadable ({err})")
    out: dict[str, VehicleSamples] = {}
    for v, by_id in recs.items():
        if not by_id:
            continue
        ordered = [by_id[k] for k in sorted(by_id)]
        stages: dict[str, list[int]] = {}
        for r in ordered:
            if r.status is FrameStatus.OK and is_sane(r)[0]:
                for name, ns in r.stages_ns().items():
                    stages.setdefault(name, []).append(ns)
        dropped = np.array([1.0 if r.status is FrameStatus.DROPPED else 0.0 for r in ordered
                            if r.status in _ACCOUNTED])
        out[v] = VehicleSamples({k: np.asarray(x, np.float64) / 1e6 for k, x in stages.items()}, dropped)
    missing = [v for v in vehicles if v not in out]
    return RunSamples(out, f"no pipeline records for {', '.join(missing)}" if missing else "")


# What ``load_run(..., unfinished=True)`` gives for a run that did not finish.
UNFINISHED = "did not finish (no summary.json, only run.mcap: killed or crashed; see hil report)"


def load_run(path: str | os.PathLike[str], *, unfinished: bool = False) -> tuple[dict[str, Any], RunSamples]:
    """A run's ``summary.json`` and its per-frame samples. With ``unfinished``, a run
    folder holding ``run.mcap`` but no ``summary.json`` (a run killed or crashed) is a
    summary of no vehicle with ``ended_by`` :data:`UNFINISHED` (the RUN that
    ``hil compare`` judges: a run that ended early is a regression, not bad input).

    Raises:
        ConfigError: not a run folder, or its ``summary.json`` is missing or bad
            (``hil.harness.record.run_folder.load_summary``). A missing or unreadable
            ``run.mcap`` is not an error: the samples are then empty, with a note.
    """
    p = Path(path)
    if unfinished and p.is_dir() and (p / MCAP_NAME).is_file() and not (p / SUMMARY_NAME).is_file():
        return {"vehicles": {}, "ended_by": UNFINISHED}, RunSamples({}, "")
    summary = load_summary(path)
    return summary, read_samples(run_dir_of(path), list(summary["vehicles"]))


__all__ = ["RunSamples", "VehicleSamples", "load_run", "read_samples"]
