"""Training data for the CNN target (``targets/cnn``): simulator frames with labels
from ground truth.

    python -m hil.training.dataset OUT_DIR --seed 0 --train 3000 --val 500

Every sample is one 320x240 camera frame as the wire carries it (JPEG, quality
drawn from 70-95) with

* the visible boxes of every entity the camera shows (``Simulation.camera_truth``:
  segmentation, occlusion-aware) and their class: vehicle, pedestrian, obstacle;
* the steering angle of an expert that follows the lane centre: pure pursuit on the
  ego's true lane centre line (its route) with the target point ``LOOKAHEAD_M`` =
  8 m ahead of the camera (10.3 m from the vehicle centre, the yaw pivot of the
  bicycle model, wheelbase 2.7 m), clamped to +-0.5 rad. From an offset or yawed
  pose that is the steering that returns to the centre, so perturbed poses give
  recovery labels (Bojarski et al. 2016 used shifted and rotated views for this).

Two sources, drawn 60/40 (``COMPOSED_SHARE``; a drive ends early once the car has
stood still for two frames, so about 70 % of the frames come from composed worlds):

* composed worlds: a two-lane road of random straights and arcs (radius 60-800 m),
  static cars of random size and paint (the eight scenario paints and any other hue,
  blue and green included), pedestrians and obstacles in the lanes and on the
  shoulders; the ego is placed at random along its lane, 60 % of poses near the
  centre (sigma 0.25 m, 0.02 rad), 40 % anywhere within +-1.3 m and +-0.12 rad;
* registered scenarios (stopped_car, curved_road, cut_in, lead_brake,
  pedestrian_occluded) with random parameters and seeds, driven by the expert
  (steering as above; speed held, braking to stop 5 m behind whatever ground truth
  puts in its path); every 0.5 s a frame, half of them from a pose shifted and
  rotated for that frame only.

Everything is drawn from ``numpy.random.default_rng`` seeded by ``(seed, split)``:
the same seed writes the same frames on the same machine (software rendering).
Training uses seed 0 (``hil train``); tests draw held-out frames with seeds from
``HELDOUT_SEED_BASE`` on, never used in training.

On disk: ``OUT/{train,val}/images/NNNNN.jpg``, ``OUT/{split}/labels.jsonl`` (one
JSON object per frame, same order) and ``OUT/meta.json``.

Call ``hil.scenarios.gl.select_backend()`` before generating (the simulator is imported
when the first world is built).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from hil.common.classes import ObjectClass
from hil.scenarios import get as get_scenario
from hil.scenarios.path import Path as RoadPath
from hil.scenarios.road import RoadSpec
from hil.scenarios.vehicle import VehicleLimits
from hil.scenarios.world import PAINTS, PEDESTRIAN_SIZE_M, CameraSpec, VehicleSpec, WorldSpec

if TYPE_CHECKING:
    from hil.scenarios.sim import Simulation

LOOKAHEAD_M = 8.0       # expert's target point ahead of the camera, m
MAX_STEER_RAD = 0.5
CONTROL_PERIOD_STEPS = 25  # 20 Hz at the 2 ms physics step
COMPOSED_SHARE = 0.6
FRAMES_PER_WORLD = 24
FRAMES_PER_DRIVE = 16
HELDOUT_SEED_BASE = 10_000
SPLITS = ("train", "val")
_LANE_W = 3.7


@dataclass(frozen=True)
class LabelBox:
    """One entity in a frame: class ("vehicle", "pedestrian", "obstacle"), box in
    pixels (x0, y0, x1, y1; x1, y1 exclusive), visible pixels and fraction,
    whether the silhouette runs past the border, distance along and offset from the
    ego's path (m)."""

    cls: str
    box_px: tuple[int, int, int, int]
    visible_px: int
    visible_fraction: float
    truncated: bool
    path_s_m: float
    path_lateral_m: float


@dataclass(frozen=True)
class Sample:
    """One labelled frame. ``camera`` = (fx, fy, cx, cy, mount_height_m, pitch_rad);
    ``lateral_m``/``heading_err_rad``: the ego's offset from its lane centre (left
    positive) and its heading relative to the lane, for analysis."""

    jpeg: bytes
    boxes: tuple[LabelBox, ...]
    steering_rad: float
    speed_mps: float
    lateral_m: float
    heading_err_rad: float
    camera: tuple[float, float, float, float, float, float]
    source: str

    def label_json(self) -> dict[str, object]:
        d = asdict(self)
        del d["jpeg"]
        return d


# -- the expert -----------------------------------------------------------------


def _route(sim: Simulation, vehicle: str) -> RoadPath:
    return next(v for v in sim.world.vehicles if v.name == vehicle).route_path()


def expert_steering(sim: Simulation, vehicle: str, *, lookahead_m: float = LOOKAHEAD_M) -> float:
    """Pure pursuit (rad, positive left) about the vehicle centre towards the point of
    the true lane centre ``lookahead_m`` ahead of the camera, clamped to +-0.5 rad."""
    x, y, yaw = sim.pose(vehicle)
    route = _route(sim, vehicle)
    s, _ = route.project(x, y)
    tx, ty, _ = route.pose_at(float(s) + sim.world.camera.mount_forward_m + lookahead_m)
    dx, dy = float(tx) - x, float(ty) - y
    xl = math.cos(yaw) * dx + math.sin(yaw) * dy
    yl = -math.sin(yaw) * dx + math.cos(yaw) * dy
    steer = math.atan2(2 * VehicleLimits().wheelbase_m * yl, xl * xl + yl * yl)
    return max(-MAX_STEER_RAD, min(MAX_STEER_RAD, steer))


def lane_pose_error(sim: Simulation, vehicle: str) -> tuple[float, float]:
    """(lateral offset m, left positive; heading error rad) of the vehicle centre from
    its lane centre line."""
    x, y, yaw = sim.pose(vehicle)
    route = _route(sim, vehicle)
    s, lat = route.project(x, y)
    _, _, h = route.pose_at(float(s))
    return float(lat), float((yaw - float(h) + math.pi) % (2 * math.pi) - math.pi)


# -- one frame --------------------------------------------------------------------


def _capture(sim: Simulation, vehicle: str, rng: np.random.Generator, source: str) -> Sample:
    rgb = sim.render(vehicle)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           (cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(70, 96))))
    if not ok:  # pragma: no cover - OpenCV failing on a valid array
        raise RuntimeError("JPEG encoding failed")
    truth = sim.camera_truth(vehicle)
    boxes = tuple(LabelBox(b.cls, b.box_px, int(b.visible_px), float(b.visible_fraction),
                           bool(b.truncated), float(b.path_s_m), float(b.path_lateral_m)) for b in truth.boxes)
    k = sim.intrinsics()
    cam = sim.world.camera
    lat, dyaw = lane_pose_error(sim, vehicle)
    return Sample(buf.tobytes(), boxes, expert_steering(sim, vehicle), max(0.0, sim.speed_mps(vehicle)),
                  lat, dyaw, (k.fx, k.fy, k.cx, k.cy, cam.mount_height_m, cam.pitch_rad), source)


def _perturbation(rng: np.random.Generator, *, wide: bool) -> tuple[float, float]:
    """(lateral m, yaw rad) offset of a pose from its lane centre."""
    if wide:
        return float(rng.uniform(-1.3, 1.3)), float(rng.uniform(-0.12, 0.12))
    return float(np.clip(rng.normal(0, 0.25), -1.3, 1.3)), float(np.clip(rng.normal(0, 0.02), -0.12, 0.12))


def _clear_of_entities(sim: Simulation, x: float, y: float, yaw: float, ego: str) -> bool:
    """True when no other entity's footprint comes within 0.5 m (ahead/behind) or
    0.3 m (sideways) of the ego's at pose (x, y, yaw)."""
    c, s = math.cos(yaw), math.sin(yaw)
    for v in sim.world.vehicles:
        if v.name == ego:
            continue
        ex, ey, _ = sim.pose(v.name)
        dx, dy = ex - x, ey - y
        fx, fy = c * dx + s * dy, -s * dx + c * dy
        reach = math.hypot(v.size_m[0], v.size_m[1]) / 2
        if abs(fx) < 2.25 + reach + 0.5 and abs(fy) < 0.9 + reach + 0.3:
            return False
    return True


# -- composed worlds --------------------------------------------------------------


def _paint(rng: np.random.Generator) -> tuple[float, float, float, float]:
    if rng.random() < 0.5:
        return PAINTS[int(rng.integers(len(PAINTS)))]
    hsv = np.array([[[rng.integers(0, 180), rng.integers(60, 256), rng.integers(70, 256)]]], np.uint8)
    r, g, b = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0] / 255.0
    return (float(r), float(g), float(b), 1.0)


def _road_path(rng: np.random.Generator) -> RoadPath:
    path = RoadPath.start(-30.0, 0.0, 0.0).line(float(rng.uniform(30, 80)))
    for _ in range(int(rng.integers(2, 5))):
        if rng.random() < 0.6:
            radius = float(np.exp(rng.uniform(math.log(60), math.log(800))))
            angle = math.radians(float(rng.uniform(10, 70))) * (1 if rng.random() < 0.5 else -1)
            angle = math.copysign(min(abs(angle), 150.0 / radius), angle)  # at most 150 m of arc
            path = path.arc(radius, angle)
        else:
            path = path.line(float(rng.uniform(20, 120)))
    return path.line(150.0)


def _composed_world(rng: np.random.Generator, camera: CameraSpec) -> tuple[WorldSpec, list[float]]:
    """A random road with static traffic; returns the world and the arc lengths (on
    the ego's lane) of the entities."""
    road = RoadSpec(path=_road_path(rng), lane_width_m=_LANE_W, shoulder_m=float(rng.uniform(0.5, 3.0)))
    lane0 = road.lane(0)
    length = lane0.length_m
    ego = VehicleSpec("ego0", x_m=float(lane0.pose_at(1.0)[0]), y_m=float(lane0.pose_at(1.0)[1]),
                      yaw_rad=float(lane0.pose_at(1.0)[2]), ego=True, route=lane0)
    placed: list[VehicleSpec] = []
    s_list: list[float] = []
    n_cars, n_peds, n_obst = int(rng.poisson(3.0)), int(rng.poisson(2.0)), int(rng.poisson(1.8))
    kinds = ["car"] * n_cars + ["ped"] * n_peds + ["obstacle"] * n_obst
    for i, kind in enumerate(kinds):
        for _ in range(20):  # tries to find a free spot
            s = float(rng.uniform(20.0, length - 40.0))
            where = rng.random()
            if kind == "car":
                size = (float(rng.uniform(3.8, 5.2)), float(rng.uniform(1.6, 2.0)),
                        float(rng.uniform(2.0, 2.5) if rng.random() < 0.1 else rng.uniform(1.3, 1.7)))
                lat = (float(rng.normal(0, 0.3)) if where < 0.55 else _LANE_W + float(rng.normal(0, 0.3))
                       if where < 0.85 else -_LANE_W / 2 - 0.3 - size[1] / 2 - float(rng.uniform(0, 1)))
                dyaw = float(rng.normal(0, 0.05)) if rng.random() < 0.9 else float(rng.uniform(-1.6, 1.6))
                cls, rgba = ObjectClass.VEHICLE, _paint(rng)
            elif kind == "ped":
                size = PEDESTRIAN_SIZE_M
                lat = (float(rng.uniform(-1.5, 1.5)) if where < 0.5
                       else -_LANE_W / 2 - float(rng.uniform(0.3, 2.0)))
                dyaw = float(rng.uniform(-math.pi, math.pi))
                cls = ObjectClass.PEDESTRIAN
                rgba = (1.0, 0.55, 0.0, 1.0) if rng.random() < 0.5 else _paint(rng)
            else:
                size = (float(rng.uniform(0.3, 1.0)), float(rng.uniform(0.4, 1.0)), float(rng.uniform(0.4, 1.0)))
                lat = float(rng.uniform(-1.5, 1.5)) if where < 0.7 else -_LANE_W / 2 - float(rng.uniform(0.3, 1.5))
                dyaw = float(rng.uniform(-0.8, 0.8))
                cls = ObjectClass.OBSTACLE
                grey = float(rng.uniform(0.6, 0.95))  # lighter than the road (0.32)
                rgba = _paint(rng) if rng.random() < 0.6 else (grey, grey * 0.9, grey * 0.8, 1.0)
            bx, by, bh = (float(v) for v in lane0.pose_at(s))
            x, y = bx - lat * math.sin(bh), by + lat * math.cos(bh)
            spec = VehicleSpec(f"{kind}{i}", x_m=x, y_m=y, yaw_rad=bh + dyaw, rgba=rgba, size_m=size, cls=cls)
            reach = math.hypot(size[0], size[1]) / 2
            if all(math.hypot(p.x_m - x, p.y_m - y) > reach + math.hypot(p.size_m[0], p.size_m[1]) / 2 + 0.3
                   for p in placed):
                placed.append(spec)
                s_list.append(s)
                break
    world = WorldSpec(roads=(road,), vehicles=(ego, *placed), camera=camera, physics_step_s=0.002)
    return world, s_list


def _composed_samples(rng: np.random.Generator, n: int, camera: CameraSpec) -> Iterator[Sample]:
    from hil.scenarios.sim import Simulation

    world, s_list = _composed_world(rng, camera)
    lane0 = world.vehicles[0].route_path()
    with Simulation(world) as sim:
        made = tries = 0
        while made < n and tries < 4 * n:
            tries += 1
            if s_list and rng.random() < 0.75:  # something ahead, 2-50 m from the bumper, mostly near
                s = s_list[int(rng.integers(len(s_list)))] - 2.25 - 2.0 - 48.0 * float(rng.random()) ** 1.5
            else:
                s = float(rng.uniform(5.0, lane0.length_m - 60.0))
            s = max(1.0, s)
            lat, dyaw = _perturbation(rng, wide=rng.random() < 0.4)
            bx, by, bh = (float(v) for v in lane0.pose_at(s))
            x, y, yaw = bx - lat * math.sin(bh), by + lat * math.cos(bh), bh + dyaw
            if not _clear_of_entities(sim, x, y, yaw, "ego0"):
                continue
            sim.set_pose("ego0", x_m=x, y_m=y, yaw_rad=yaw)
            made += 1
            yield _capture(sim, "ego0", rng, "composed")


# -- registered scenarios, driven by the expert -----------------------------------


def _scenario_params(name: str, rng: np.random.Generator) -> dict[str, float]:
    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    if name == "stopped_car":
        return {"gap_m": u(15, 120), "ego_speed_mps": u(4, 12), "lateral_offset_m": u(-1, 1)}
    if name == "curved_road":
        lead = u(15, 60) if rng.random() < 0.5 else 0.0
        return {"radius_m": u(60, 500), "arc_deg": u(15, 90), "ego_speed_mps": u(5, 12), "lead_gap_m": lead,
                "lead_speed_mps": u(3, 9)}
    if name == "cut_in":
        v = u(6, 12)
        return {"ego_speed_mps": v, "npc_speed_mps": v + u(1, 4), "start_ahead_m": u(-5, 15),
                "cut_in_at_s": u(0.5, 3), "final_speed_mps": u(3, 8)}
    if name == "lead_brake":
        return {"speed_mps": u(5, 12), "gap_m": u(10, 40), "brake_at_s": u(1, 4), "decel_mps2": u(3, 8)}
    if name == "pedestrian_occluded":
        return {"ego_speed_mps": u(4, 10), "parked_gap_m": u(15, 50), "step_out_s": u(0, 3)}
    raise ValueError(f"no parameter ranges for scenario {name!r}")


SCENARIO_WEIGHTS = {"stopped_car": 0.35, "curved_road": 0.35, "cut_in": 0.1, "lead_brake": 0.1,
                    "pedestrian_occluded": 0.1}


def _expert_longitudinal(sim: Simulation, vehicle: str, v_des: float) -> tuple[float, float]:
    ego = sim.ground_truth().ego(vehicle)
    v = ego.speed_mps
    target = v_des
    if ego.gap_m is not None:
        target = min(target, max(0.0, ego.obstacle_speed_mps) + math.sqrt(6.0 * max(0.0, ego.gap_m - 5.0)))
    if v < target:
        return min(1.0, 0.5 * (target - v)), 0.0
    return 0.0, min(1.0, 0.3 * (v - target) + (0.3 if target < 0.1 else 0.0))


def _drive_samples(rng: np.random.Generator, name: str, n: int, camera: CameraSpec) -> Iterator[Sample]:
    params = _scenario_params(name, rng)
    world = get_scenario(name).build(params=params, seed=int(rng.integers(1 << 30)), camera=camera,
                                     physics_step_s=0.002)
    from hil.scenarios.sim import Simulation

    v_des = max(3.0, params.get("ego_speed_mps", params.get("speed_mps", 8.0)))
    period = 10  # control ticks between frames: 0.5 s
    with Simulation(world) as sim:
        ego = sim.egos[0]
        tick = -int(rng.integers(0, period))
        made = still = 0
        while made < n and still <= 2:  # two frames standing still are enough
            steer = expert_steering(sim, ego)
            throttle, brake = _expert_longitudinal(sim, ego, v_des)
            sim.set_control(ego, steering_rad=steer, throttle=throttle, brake=brake)
            if tick >= 0 and tick % period == 0:
                still = still + 1 if sim.speed_mps(ego) < 0.1 else 0
                pose = sim.pose(ego)
                moved = False
                if rng.random() < 0.5:
                    lat, dyaw = _perturbation(rng, wide=rng.random() < 0.5)
                    x, y, yaw = pose[0] - lat * math.sin(pose[2]), pose[1] + lat * math.cos(pose[2]), pose[2] + dyaw
                    if _clear_of_entities(sim, x, y, yaw, ego):
                        sim.set_pose(ego, x_m=x, y_m=y, yaw_rad=yaw)
                        moved = True
                made += 1
                yield _capture(sim, ego, rng, name)
                if moved:
                    sim.set_pose(ego, x_m=pose[0], y_m=pose[1], yaw_rad=pose[2])
            for _ in range(CONTROL_PERIOD_STEPS):
                sim.step()
            tick += 1


# -- splits --------------------------------------------------------------------------


def generate(*, seed: int, n_frames: int, split: int = 0, camera: CameraSpec | None = None) -> Iterator[Sample]:
    """``n_frames`` labelled frames, deterministic in ``(seed, split)``.

    Raises:
        SimulationError: a world does not build or render.
    """
    cam = camera or CameraSpec()
    rng = np.random.default_rng([seed, split])
    names = list(SCENARIO_WEIGHTS)
    weights = np.array([SCENARIO_WEIGHTS[k] for k in names])
    made = 0
    while made < n_frames:
        left = n_frames - made
        if rng.random() < COMPOSED_SHARE:
            gen = _composed_samples(rng, min(left, FRAMES_PER_WORLD), cam)
        else:
            name = names[int(rng.choice(len(names), p=weights / weights.sum()))]
            gen = _drive_samples(rng, name, min(left, FRAMES_PER_DRIVE), cam)
        for sample in gen:
            made += 1
            yield sample


def write_split(out_dir: Path, samples: Iterator[Sample]) -> int:
    """Write ``samples`` as ``out_dir/images/NNNNN.jpg`` + ``out_dir/labels.jsonl``;
    returns how many."""
    img_dir = out_dir / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    n = 0
    with open(out_dir / "labels.jsonl", "w") as f:
        for n, s in enumerate(samples, 1):
            name = f"{n - 1:05d}.jpg"
            (img_dir / name).write_bytes(s.jpeg)
            f.write(json.dumps({"image": name, **s.label_json()}) + "\n")
    return n


def read_split(split_dir: Path) -> list[Sample]:
    """The samples of one split written by ``write_split``.

    Raises:
        FileNotFoundError: no ``labels.jsonl`` in ``split_dir``.
    """
    out = []
    with open(split_dir / "labels.jsonl") as f:
        for line in f:
            d = json.loads(line)
            boxes = tuple(LabelBox(b["cls"], tuple(b["box_px"]), b["visible_px"], b["visible_fraction"],
                                   b["truncated"], b["path_s_m"], b["path_lateral_m"]) for b in d["boxes"])
            out.append(Sample((split_dir / "images" / d["image"]).read_bytes(), boxes, d["steering_rad"],
                              d["speed_mps"], d["lateral_m"], d["heading_err_rad"], tuple(d["camera"]),
                              d["source"]))
    return out


def split_digest(split_dir: Path) -> str:
    """SHA-256 of a split's labels and image bytes, in order: two renders of the same
    seed on the same machine give the same digest."""
    h = hashlib.sha256()
    with open(split_dir / "labels.jsonl", "rb") as f:
        for line in f:
            h.update(line)
            h.update((split_dir / "images" / json.loads(line)["image"]).read_bytes())
    return h.hexdigest()


def _counted(frames: Iterator[Sample], *, total: int, first: int, log: Callable[[str], None]) -> Iterator[Sample]:
    """``frames``, saying every tenth of ``total`` how many are rendered and the time left."""
    import time

    from hil.common.eta import time_left

    t0, step = time.monotonic(), max(1, total // 10)
    for i, s in enumerate(frames, first + 1):
        yield s
        if i % step == 0 or i == total:
            dt = time.monotonic() - t0
            log(f"dataset: {i} of {total} frames rendered ({dt:.0f} s, {time_left(i - first, total - first, dt)})")


def build_dataset(out_dir: Path, *, seed: int, n_train: int, n_val: int,
                  log: Callable[[str], None] | None = None) -> dict[str, object]:
    """Write the train and validation splits and ``meta.json``; returns the meta.
    ``log``: a line every tenth of the frames, with the time left."""
    out_dir.mkdir(parents=True, exist_ok=True)
    counts, digests = {}, {}
    done = 0
    for k, (split, n) in enumerate(zip(SPLITS, (n_train, n_val))):
        frames: Iterator[Sample] = generate(seed=seed, n_frames=n, split=k)
        if log is not None:
            frames = _counted(frames, total=n_train + n_val, first=done, log=log)
        counts[split] = write_split(out_dir / split, frames)
        done += n
        digests[split] = split_digest(out_dir / split)
    meta = {"seed": seed, "frames": counts, "sha256": digests, "lookahead_m": LOOKAHEAD_M,
            "composed_share": COMPOSED_SHARE,
            "scenario_weights": SCENARIO_WEIGHTS, "image": [320, 240], "encoding": "jpeg q70-95"}
    (out_dir / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hil.training.dataset", description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path, help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--train", type=int, default=3000, help="training frames")
    p.add_argument("--val", type=int, default=500, help="validation frames")
    a = p.parse_args(argv)
    print(json.dumps(build_dataset(a.out, seed=a.seed, n_train=a.train, n_val=a.val), indent=2))
    return 0


if __name__ == "__main__":
    from hil.scenarios.gl import select_backend

    select_backend()
    raise SystemExit(main())
