"""Lockstep latency profiles: delay each estimate's control in simulated time.

In lockstep the simulation waits for every estimate, so by itself latency has no
physical consequence. A profile gives each frame a latency; the estimate's control
is held and applied when sim time reaches ``sim_time_of_capture + latency`` (rounded
up to the physics step), exactly as a real-time run with that latency would have
applied it — so a timing situation found in real time replays exactly.

Profiles (``lockstep.latency.kind`` in the config):

* ``constant``: ``ms`` for every frame;
* ``normal`` / ``lognormal``: drawn per frame (``ms`` is the mean / median; ``std_ms``
  / ``sigma`` the spread), clipped to ``[min_ms, max_ms]``. Vehicle ``i``'s frame
  ``k`` always gets the ``k``-th draw of a generator seeded with ``(seed, i)``, so the
  order in which answers arrive never changes the run;
* ``recorded``: the per-frame latencies of a recorded run (its ``/<vehicle>/pipeline``
  records), matched by vehicle name and frame order and repeated cyclically past its
  end. A camera rig's records (they carry ``camera``) are replayed camera by camera:
  a rig's camera ``k`` at frame set ``s`` gets the recorded camera ``k``'s ``s``-th
  frame (camera 0's where the recording has no camera ``k``), a single camera gets
  camera 0's in order. ``stage: sim_apply`` replays ``sim_time_apply - sim_time``
  (what that run's simulation saw); ``to_apply``/``end_to_end`` replay wall-clock
  stages times that run's real-time factor. A frame that run dropped (or answered
  stale) is dropped (stale) again.

On top of any profile, ``camera_ms`` and ``camera_drop_prob`` make a named camera of
the rig slower, or lose its frames (seeded per vehicle and frame), as ``hil search``
draws them; a single camera is camera 0.

Held controls are queued by due sim time (a bounded heap: at most one entry per frame
in flight, which lockstep already bounds).
"""

from __future__ import annotations

import heapq
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.common.errors import ConfigError
from hil.harness.config.model import LatencyConfig, LatencyKind, LatencyStage
from hil.timing.records import FrameStatus

_BLOCK = 1024


@dataclass(frozen=True)
class Delay:
    """A frame's fate under a profile: applied after ``latency_ns`` of sim time, or
    not at all (``status`` DROPPED or STALE, as the recording had it)."""

    latency_ns: int | None
    status: FrameStatus = FrameStatus.OK


class LatencyProfile:
    """Per-frame latencies of one run's vehicles."""

    def __init__(self, cfg: LatencyConfig, *, seed: int, vehicles: Sequence[str],
                 cameras: Sequence[str] = ()) -> None:
        """``cameras``: the rig's camera names, camera 0 first (``camera_ms`` and
        ``camera_drop_prob`` name them)."""
        self.cfg = cfg
        self._cameras = list(cameras)
        self.kind = cfg.kind
        self._seed = seed
        self._vehicles = list(vehicles)
        self._blocks: dict[int, np.ndarray] = {}
        self._recorded: dict[str, dict[int, list[Delay]]] = {}  # vehicle -> camera -> frame order
        if cfg.kind == LatencyKind.RECORDED:
            self._recorded = _read_recorded(cfg, self._vehicles)

    def describe(self) -> dict[str, object]:
        c = self.cfg
        out: dict[str, object] = {"kind": c.kind.value}
        if c.drop_prob > 0:
            out["drop_prob"] = c.drop_prob
        if c.kind == LatencyKind.CONSTANT:
            out["ms"] = c.ms
        elif c.kind == LatencyKind.NORMAL:
            out |= {"mean_ms": c.ms, "std_ms": c.std_ms, "min_ms": c.min_ms, "max_ms": c.max_ms}
        elif c.kind == LatencyKind.LOGNORMAL:
            out |= {"median_ms": c.ms, "sigma": c.sigma, "min_ms": c.min_ms, "max_ms": c.max_ms}
        elif c.kind == LatencyKind.RECORDED:
            out |= {"path": c.path, "stage": c.stage.value}
        for group in ("camera_ms", "camera_drop_prob"):
            if any(getattr(c, group).values()):
                out[group] = dict(getattr(c, group))
        return out

    def delay(self, vehicle_index: int, frame_id: int, *, camera: int | None = None,
              frame_set: int | None = None) -> Delay:
        """The delay of frame ``frame_id`` of the ``vehicle_index``-th vehicle; a rig's
        frame names its ``camera`` and the index of its ``frame_set`` (the replay of a
        recorded rig is per camera), with the camera's own share (a single camera: camera 0's)."""
        d = self._profile(vehicle_index, frame_id, camera=camera, frame_set=frame_set)
        k = camera or 0
        name = self._cameras[k] if k < len(self._cameras) else None
        if name is None or d.latency_ns is None:
            return d
        p = self.cfg.camera_drop_prob.get(name, 0.0)
        if p > 0 and np.random.default_rng([self._seed, vehicle_index, frame_id, 0xCA]).random() < p:
            return Delay(None, FrameStatus.DROPPED)
        return Delay(d.latency_ns + round(self.cfg.camera_ms.get(name, 0.0) * 1e6))

    def _profile(self, vehicle_index: int, frame_id: int, *, camera: int | None, frame_set: int | None) -> Delay:
        c = self.cfg
        if c.kind == LatencyKind.RECORDED:
            cams = self._recorded[self._vehicles[vehicle_index]]
            first = cams[min(cams)]  # camera 0 (a single camera's records are its)
            if camera is None or frame_set is None:
                return first[frame_id % len(first)]
            seq = cams.get(camera, first)
            return seq[frame_set % len(seq)]
        if c.drop_prob > 0:
            rng = np.random.default_rng([self._seed, vehicle_index, frame_id, 0xD0])
            if rng.random() < c.drop_prob:
                return Delay(None, FrameStatus.DROPPED)
        if c.kind == LatencyKind.NONE:
            return Delay(0)
        if c.kind == LatencyKind.CONSTANT:
            return Delay(round(c.ms * 1e6))
        block = frame_id // _BLOCK
        key = vehicle_index * 1_000_000 + block
        draws = self._blocks.get(key)
        if draws is None:
            rng = np.random.default_rng([self._seed, vehicle_index, block])
            if c.kind == LatencyKind.NORMAL:
                draws = rng.normal(c.ms, c.std_ms, _BLOCK)
            else:
                draws = math.log(max(c.ms, 1e-6)) + c.sigma * rng.standard_normal(_BLOCK)
                draws = np.exp(draws)
            draws = np.clip(draws, c.min_ms, c.max_ms)
            self._blocks[key] = draws
        return Delay(round(float(draws[frame_id % _BLOCK]) * 1e6))


@dataclass(order=True)
class Held:
    """A control waiting for its sim time (``due_sim_ns``)."""

    due_sim_ns: int
    vehicle_id: int
    frame_id: int
    item: object = field(compare=False)


class HeldControls:
    """Controls waiting to be applied, ordered by due sim time, then vehicle, then
    frame (deterministic whatever order the answers came in)."""

    def __init__(self, profile: LatencyProfile, *, step_ns: int) -> None:
        self.profile = profile
        self.step_ns = step_ns
        self._heap: list[Held] = []

    def __len__(self) -> int:
        return len(self._heap)

    def due_time(self, capture_sim_ns: int, latency_ns: int) -> int:
        """Capture time plus latency, rounded up to the physics step grid."""
        t = capture_sim_ns + max(0, latency_ns)
        return -(-t // self.step_ns) * self.step_ns

    def hold(self, due_sim_ns: int, vehicle_id: int, frame_id: int, item: object) -> None:
        heapq.heappush(self._heap, Held(due_sim_ns, vehicle_id, frame_id, item))

    def pop_due(self, sim_now_ns: int) -> list[Held]:
        out = []
        while self._heap and self._heap[0].due_sim_ns <= sim_now_ns:
            out.append(heapq.heappop(self._heap))
        return out

    def next_due(self) -> int | None:
        """The earliest due sim time (ns) held, or None."""
        return self._heap[0].due_sim_ns if self._heap else None

    def pop_all(self) -> list[Held]:
        out = sorted(self._heap)
        self._heap = []
        return out


def _read_recorded(cfg: LatencyConfig, vehicles: Sequence[str]) -> dict[str, dict[int, list[Delay]]]:
    """Per vehicle and camera (0 for records without one): the Delays of a recorded
    run's pipeline records in frame order.

    Raises:
        ConfigError: the file is missing or unreadable, or lacks a vehicle's records.
    """
    from mcap.reader import make_reader

    path = Path(cfg.path or "")
    if path.is_dir():
        path = path / "run.mcap"
    topics = [f"/{v}/pipeline" for v in vehicles]
    recs: dict[str, dict[int, dict[str, object]]] = {v: {} for v in vehicles}
    factor = 1.0
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for rec in reader.iter_metadata():
                if rec.name == "config" and "yaml_json" in rec.metadata:
                    factor = float(json.loads(rec.metadata["yaml_json"]).get("realtime_factor", 1.0))
            f.seek(0)
            reader = make_reader(f)
            for _, channel, message in reader.iter_messages(topics=topics):
                d = json.loads(message.data)
                recs[channel.topic[1:].rsplit("/", 1)[0]][int(d["frame_id"])] = d
    except (OSError, ValueError, KeyError) as err:
        raise ConfigError(f"lockstep.latency.path: cannot read pipeline records from {path}: {err}") from err
    out: dict[str, dict[int, list[Delay]]] = {}
    for v in vehicles:
        if not recs[v]:
            raise ConfigError(f"lockstep.latency.path: {path} has no pipeline records for vehicle {v!r}")
        cams: dict[int, list[Delay]] = {}
        for fid in sorted(recs[v]):
            d = recs[v][fid]
            camera = d.get("camera")
            cams.setdefault(camera if isinstance(camera, int) else 0, []).append(_delay_of(d, cfg.stage, factor))
        out[v] = cams
    return out


def _delay_of(d: dict[str, object], stage: LatencyStage, factor: float) -> Delay:
    status = FrameStatus(str(d["status"]))
    if status == FrameStatus.DROPPED:
        return Delay(None, FrameStatus.DROPPED)
    if status == FrameStatus.STALE:
        return Delay(None, FrameStatus.STALE)
    if stage == LatencyStage.SIM_APPLY and d.get("sim_time_apply_ns") is not None:
        return Delay(int(d["sim_time_apply_ns"]) - int(d["sim_time_ns"]))  # type: ignore[call-overload]
    a, b = ("t_apply_ns", "t0_ns") if stage != LatencyStage.END_TO_END else ("t0p_ns", "t0_ns")
    if d.get(a) is None:
        return Delay(None, FrameStatus.DROPPED)
    return Delay(round((int(d[a]) - int(d[b])) * factor))  # type: ignore[call-overload]
