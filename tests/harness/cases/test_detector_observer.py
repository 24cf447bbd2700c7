"""The detector observer on a real Simulation (no rendering): truth at t0 from the
frame's own instant, camera truth that arrives after the estimate, the applying
ego's truth only."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from hil.adapters.wire.messages import Control, DrivingState, Estimate
from hil.harness.cases.detector import MismatchKind
from hil.harness.cases.detector_observer import DetectorObserver
from hil.harness.config.detector import DetectorSettings
from hil.harness.config.model import CameraConfig
from hil import scenarios
from hil.scenarios.ground_truth import CameraTruth, EntityTable, GroundTruth, RefStateRules
from hil.scenarios.sim import Simulation
from hil.scenarios.world import CameraSpec
from hil.timing.records import FrameStatus, PipelineRecord

MS = 1_000_000


class Events:
    def __init__(self) -> None:
        self.events: list[dict] = []

    def write_json(self, topic: str, obj: dict, **_kw: int) -> bool:
        self.events.append(obj)
        return True


@pytest.fixture
def sim():
    sdef = scenarios.get("stopped_car")
    world = sdef.build(params=sdef.resolve({"gap_m": 15.0, "ego_speed_mps": 12.0}), seed=1, physics_step_s=0.002,
                       camera=CameraSpec())
    with Simulation(world, rules=RefStateRules()) as s:
        yield s


def blind(frame_id: int) -> Estimate:
    return Estimate(0, frame_id, DrivingState.SAFE, Control(), (), 0, 0, 0, 0)


def test_camera_truth_after_the_estimate_is_judged_in_frame_order(sim):
    rec = Events()
    obs = DetectorObserver(DetectorSettings(), ["ego0"], camera=CameraConfig(), recorder=rec, timing=None,
                           link_delay_s=0.0)
    snapshots: list[tuple[str, ...] | None] = []
    late: list[tuple[int, CameraTruth]] = []
    for f in range(6):
        for _ in range(25):
            sim.step()
        gt = sim.ground_truth()
        obs.on_truth(gt, t_ns=f * 50 * MS)
        ct = CameraTruth("ego0", gt.sim_time_ns, (), next(e for e in gt.egos if e.vehicle == "ego0"))
        for _ in range(5):
            sim.step()

        def truth_now(*, egos: tuple[str, ...] | None = None) -> GroundTruth:
            snapshots.append(egos)
            return sim.truth_snapshot()

        obs.on_apply("ego0", f, truth_now)
        record = PipelineRecord("ego0", f, gt.sim_time_ns, 0, 0, FrameStatus.OK, 0, 0, 0, 0, 1, 2, sim.sim_time_ns)
        obs.on_record("ego0", record, blind(f))  # the estimate before its camera truth
        late.append((f, ct))
        if f % 2:  # camera truths come in pairs, after both estimates
            for fid, c in late:
                obs.on_camera_truth("ego0", fid, c)
            late.clear()
    obs.finish()
    states = [e for e in rec.events if e["kind"].removeprefix("mismatch.") == MismatchKind.STATE_MISMATCH.value]
    assert [(e["cause"], e["frame_ids"]) for e in states] == [("perception", [0, 1, 2])]
    ev = states[0]["evidence"]
    assert ev["truth_t0"] == {"state": "STOP"} and ev["sim_time_apply_ns"] - ev["sim_time_t0_ns"] == 10 * MS
    assert snapshots == [("ego0",)] * 6  # only the applying ego's truth is asked for


def test_the_simulators_entity_columns_judge_as_its_entity_states():
    # The simulator's ground truth holds its entities as columns (an EntityTable), and
    # the detector reads its footprints off them without building a state per entity
    # (one instant's world 93 -> 43 us at 16 vehicles, 167 -> 50 at 64). Given the same
    # instants as a tuple of EntityState, the frame truths it keeps at t0 and at apply
    # are the same, object for object, to the bit.
    sdef = scenarios.get("multi_vehicle")
    world = sdef.build(params=sdef.resolve({"n_vehicles": 12}), seed=3, physics_step_s=0.002, camera=CameraSpec())
    kept: dict[str, list] = {}
    for way in ("columns", "states"):
        with Simulation(world, rules=RefStateRules()) as s:
            egos = list(s.egos)
            obs = DetectorObserver(DetectorSettings(), egos, camera=CameraConfig(), recorder=Events(), timing=None,
                                   link_delay_s=0.0)

            def as_asked(gt: GroundTruth) -> GroundTruth:
                assert isinstance(gt.entities, EntityTable)
                return gt if way == "columns" else replace(gt, entities=tuple(gt.entities))

            def now(*, egos: tuple[str, ...] | None = None) -> GroundTruth:
                return as_asked(s.truth_snapshot(egos=egos))

            for f in range(8):
                for _ in range(25):
                    s.step()
                gt = as_asked(s.ground_truth())
                obs.on_truth(gt, t_ns=f * 50 * MS)
                for name in egos:
                    obs.on_camera_truth(name, f, seen_by(gt, name))
                for _ in range(5):
                    s.step()
                for name in egos:
                    obs.on_apply(name, f, now)
            kept[way] = [(obs.v[name].at_t0.get(f), obs.v[name].at_apply.get(f)) for name in egos for f in range(8)]
    assert kept["columns"] == kept["states"]
    assert sum(1 for t0, ap in kept["columns"] if t0 is not None and ap is not None) >= 8
    assert any(ap.objects for _, ap in kept["columns"] if ap is not None)  # something in range to compare


def seen_by(gt: GroundTruth, ego: str) -> CameraTruth:
    """``ego``'s camera truth showing nothing: its t0 truth holds every entity in range."""
    return CameraTruth(ego, gt.sim_time_ns, (), gt.ego(ego))


# -- a camera rig (issue 31) ----------------------------------------------------------

RIG = [{"name": "front", "forward_m": 1.0, "lateral_m": 0.5, "yaw_deg": 30.0},
       {"name": "back", "forward_m": -2.0, "yaw_deg": 180.0}]


def seen(gt: GroundTruth, *entities: str) -> CameraTruth:
    from hil.scenarios.ground_truth import VisibleBox

    boxes = tuple(VisibleBox(e, 1, "vehicle", (0, 0, 50, 50), 2500, 1.0, False, 10.0, 0.0) for e in entities)
    return CameraTruth("ego0", gt.sim_time_ns, boxes, gt.ego("ego0"))


def looks_at(frame_id: int, *objects: tuple[str, float, float]) -> Estimate:
    from hil.adapters.wire.messages import DetectedObject, ObjectClass

    objs = tuple(DetectedObject(ObjectClass[c.upper()], 1.0, (0.0, 0.0, 1.0, 1.0), (x, y, 0.0)) for c, x, y in objects)
    return Estimate(0, frame_id, DrivingState.STOP, Control(), objs, 0, 0, 0, 0)


def rig_observer(rec: Events) -> DetectorObserver:
    return DetectorObserver(DetectorSettings(min_frames=1), ["ego0"], camera=CameraConfig(rig=RIG), recorder=rec,
                            timing=None, link_delay_s=0.0)


def answer_set(obs: DetectorObserver, sim: Simulation, set_id: int, est: Estimate) -> GroundTruth:
    """A two-camera set's answer: ground truth, apply, both frames' records."""
    for _ in range(25):
        sim.step()
    gt = sim.ground_truth()
    obs.on_truth(gt, t_ns=set_id * 50 * MS)
    obs.on_apply("ego0", set_id, lambda: gt)
    for k in range(2):  # one estimate answers both frames of the set
        obs.on_record("ego0", PipelineRecord("ego0", set_id + k, gt.sim_time_ns, 0, 0, FrameStatus.OK, 0, 0, 0, 0,
                                             1, 2, gt.sim_time_ns, camera=k), est)
    return gt


def test_a_rig_compares_positions_in_the_vehicle_frame_under_camera_0(sim):
    for _ in range(25):
        sim.step()
    gt = sim.ground_truth()
    me, car = gt.entity("ego0"), gt.entity("car1")
    assert me.heading_rad == car.heading_rad == 0.0
    # The vehicle frame of a rig: on the road under camera 0's mount, the vehicle's axes
    # (not camera 0's 30 degrees): the car's rear face, centred across from the mount.
    mount_y = me.y_m + 0.5
    x, y = car.x_m - car.size_m[0] / 2 - (me.x_m + 1.0), min(max(mount_y, car.y_m - 0.9), car.y_m + 0.9) - mount_y
    turned = (x * math.cos(math.radians(30)) + y * math.sin(math.radians(30)),
              -x * math.sin(math.radians(30)) + y * math.cos(math.radians(30)))  # the same point in camera 0's axes
    kinds = []
    for belief in ((x, y), turned):
        rec = Events()
        obs = rig_observer(rec)
        obs.on_truth(gt, t_ns=0)
        obs.on_apply("ego0", 0, lambda: gt)
        est = looks_at(0, ("vehicle", *belief))
        for k in range(2):
            obs.on_record("ego0", PipelineRecord("ego0", k, gt.sim_time_ns, 0, 0, FrameStatus.OK, 0, 0, 0, 0, 1, 2,
                                                 gt.sim_time_ns, camera=k), est)
        obs.on_camera_truth("ego0", 0, seen(gt, "car1"), cameras=2)
        obs.on_camera_truth("ego0", 0, seen(gt), cameras=2)
        obs.finish()
        kinds.append([e["kind"] for e in rec.events])
    assert kinds[0] == [] and kinds[1], kinds  # read in camera 0's axes, the car is elsewhere


def test_a_fused_set_waits_for_every_cameras_truth_and_judges_with_those_that_came(sim):
    rec = Events()
    obs = rig_observer(rec)
    # Set 0: camera 1's truth never comes; a ghost at 5 m shows it was judged all the same.
    gt = answer_set(obs, sim, 0, looks_at(0, ("pedestrian", 5.0, 0.0)))
    obs.on_camera_truth("ego0", 0, seen(gt), cameras=2)
    obs.on_tick(now_ns=10**18, sim_time_ns=0)
    assert rec.events == []  # still waiting for camera 1
    # Set 2: only the back camera shows the car; the blind answer missed it.
    gt = answer_set(obs, sim, 2, looks_at(2))
    obs.on_camera_truth("ego0", 2, seen(gt), cameras=2)
    obs.on_tick(now_ns=10**18, sim_time_ns=0)
    assert [e["kind"] for e in rec.events] == ["mismatch.ghost_object"]  # set 0, once set 2's truth came
    obs.on_camera_truth("ego0", 2, seen(gt, "car1"), cameras=2)
    # Set 4: the run ends before camera 1's truth; judged at the finish with camera 0's.
    gt = answer_set(obs, sim, 4, looks_at(4, ("pedestrian", 30.0, 0.0)))
    obs.on_camera_truth("ego0", 4, seen(gt), cameras=2)
    obs.finish()
    got = [(e["kind"], e["frame_ids"]) for e in rec.events]
    assert got == [("mismatch.ghost_object", [0]), ("mismatch.missed_object", [2]), ("mismatch.ghost_object", [4])]


def test_each_entity_is_seen_where_the_one_at_a_time_geometry_puts_it():
    # The observer views every entity of an instant at once (arrays); each must sit
    # exactly where nearest_point_in_camera_frame puts it alone, and only those within
    # 1.5 x the detector's range (all it ever compares) are kept, unless named.
    import random

    from hil.harness.cases.detector import nearest_point_in_camera_frame
    from hil.harness.cases.detector_observer import _Footprints
    from hil.scenarios.ground_truth import EntityState

    rnd = random.Random(7)
    ents = [EntityState(f"e{i}", "vehicle", rnd.uniform(-120, 120), rnd.uniform(-20, 20), 0.0, 0.0,
                        rnd.uniform(-math.pi, math.pi), (rnd.uniform(0.5, 6), rnd.uniform(0.5, 3), 1.5))
            for i in range(40)]
    world = _Footprints(ents)
    mount = (2.3, 0.4, math.radians(12))
    for k, me in enumerate(ents[:5]):
        seen = {o.name: o for o in world.view(k, mount, {"e3"}, only=None, within_m=75.0)}
        named = {o.name: o for o in world.view(k, mount, None, only={"e1", "e2", me.name}, within_m=None)}
        assert me.name not in seen and set(named) == {"e1", "e2"} - {me.name}
        far = 0
        for e in ents:
            if e is me:
                continue
            x, y = nearest_point_in_camera_frame(
                ego_x=me.x_m, ego_y=me.y_m, ego_yaw=me.heading_rad, mount_forward_m=2.3, mount_lateral_m=0.4,
                camera_yaw=math.radians(12), x=e.x_m, y=e.y_m, yaw=e.heading_rad, length=e.size_m[0],
                width=e.size_m[1])
            if math.hypot(x, y) <= 75.0:
                o = seen[e.name]
                assert (o.x_m, o.y_m, o.visible) == (x, y, e.name == "e3")  # to the bit
            else:
                far += 1
                assert e.name not in seen
            if e.name in named:
                assert (named[e.name].x_m, named[e.name].y_m) == (x, y)
        assert 0 < far < len(ents) - 1  # both sides of the range were tried
