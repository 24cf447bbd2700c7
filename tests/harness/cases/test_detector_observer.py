"""The detector observer on a real Simulation (no rendering): truth at t0 from the
frame's own instant, camera truth that arrives after the estimate, the applying
ego's truth only."""

from __future__ import annotations

import pytest

from hil.adapters.wire.messages import Control, DrivingState, Estimate
from hil.harness.cases.detector import MismatchKind
from hil.harness.cases.detector_observer import DetectorObserver
from hil.harness.config.detector import DetectorSettings
from hil.harness.config.model import CameraConfig
from hil import scenarios
from hil.scenarios.ground_truth import CameraTruth, GroundTruth, RefStateRules
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
