"""Does this machine carry a real-time run this large? Measured before it starts.

Up to :data:`UNMEASURED_VEHICLES` vehicles a run starts as it always did. Beyond
that (``multi_vehicle`` and ``hil study`` take up to 64), a real-time run first
renders its own cameras here for a moment and refuses, in one line naming the
measured limit, when the render workers could not keep up with every camera at the
configured rate: a real-time run that cannot render in time measures nothing. A
lockstep run waits for every frame, so it takes any number. A vehicle's frame is what
a render worker draws for it at a camera instant: every camera of the rig and, with
``truth.visible_boxes``, each one's segmentation truth too (which a measure of colour
images alone left out).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from hil.common.errors import ConfigError

UNMEASURED_VEHICLES = 16  # the cap before the harness was cut into shards (issue 24)
HEADROOM = 1.25           # a frame needs its encoding and hand-off on top of its render


@dataclass(frozen=True)
class RenderCapacity:
    """Vehicle frames per second this machine renders of a world (module docstring):
    one render worker as measured (``per_worker``), and the pool of ``workers``."""

    per_worker: float
    workers: int
    cores: int

    @property
    def frames_per_s(self) -> float:
        # Workers share the cores: more of them than cores renders no more.
        return self.per_worker * max(1, min(self.workers, self.cores))

    def vehicles_at(self, fps: float) -> int:
        """The most vehicles at ``fps`` the pool renders in time, with headroom."""
        return int(self.frames_per_s / (fps * HEADROOM))


def measure(sim: Any, *, workers: int, cores: int, seconds: float = 0.5, cameras: int = 1,
            truth_px: int | None = None) -> RenderCapacity:
    """Render the vehicles' frames in turn for about ``seconds`` (after one warm-up
    round) in this process, as one render worker would: ``cameras`` of each rig and,
    with ``truth_px`` (``truth.min_visible_px``), each one's segmentation truth."""
    egos = list(sim.egos)

    def frame(name: str) -> None:
        for k in range(cameras):
            sim.render(name, k)
            if truth_px is not None:
                sim.camera_truth(name, k, min_visible_px=truth_px)

    for name in egos[:4]:  # shaders compile on the first render
        frame(name)
    n, t0 = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - t0) < seconds or n < 8:
        frame(egos[n % len(egos)])
        n += 1
    return RenderCapacity(per_worker=n / elapsed, workers=workers, cores=cores)


def check(cfg: Any, sim: Any, *, workers: int, cores: int) -> str | None:
    """For a real-time run of more than ``UNMEASURED_VEHICLES`` vehicles: measure, and
    refuse what this machine cannot render in time. Returns a line saying what was
    measured (None when nothing was: lockstep, or few vehicles). Closes ``sim``'s
    renderer after.

    Raises:
        ConfigError: the vehicles need more frames per second than the render pool
            gives (the message names both, and how many vehicles fit).
    """
    n = len(sim.egos)
    if cfg.mode.value != "realtime" or n <= UNMEASURED_VEHICLES:
        return None
    cams = len(cfg.camera.cameras())
    truth = cfg.truth.visible_boxes
    cap = measure(sim, workers=workers, cores=cores, cameras=cams,
                  truth_px=cfg.truth.min_visible_px if truth else None)
    sim.close()
    fps = float(cfg.camera.fps)
    need = n * fps
    fits = cap.vehicles_at(fps)
    cameras = f"{cams} camera{'s' * (cams > 1)}"
    frame = f"{cameras} and {'their' if cams > 1 else 'its'} truth" if truth else cameras
    line = (f"render capacity: {cap.per_worker:.0f} vehicle frames/s ({frame}) per render worker (measured now), "
            f"{cap.frames_per_s:.0f} with {cap.workers} workers on {cap.cores} cores: {fits} vehicles at {fps:g} fps")
    if n > fits:
        raise ConfigError(f"scenario.params.n_vehicles: {n} vehicles at {fps:g} fps need {need:.0f} frames/s "
                          f"({frame} each) in real time, but this machine renders {cap.frames_per_s:.0f} (measured now: "
                          f"{cap.per_worker:.0f} per render worker, {cap.workers} workers on {cap.cores} cores), so "
                          f"it carries {fits} vehicles at {fps:g} fps with {HEADROOM:g}x headroom; use at most "
                          f"{fits} vehicles, camera.fps <= {math.floor(cap.frames_per_s / (n * HEADROOM)):g}, or "
                          "mode: lockstep")
    return line
