"""The corner-case detector's work per estimate against the number of vehicles.

For N = 1, 4, 16 egos of the ``multi_vehicle`` scenario (a real ``Simulation``, no
rendering), each frame: ground truth at the camera instant (``on_truth``), the
camera truth (``on_camera_truth``, no visible boxes), then per estimate the apply
hook (``on_apply``, which takes the truth at apply) and the judgement
(``on_record``). Times the per-estimate part (``on_apply`` + ``on_record``), two
ways:

* ``all egos``: ``truth_now()`` computes every ego's truth (what the loop passed
  before issue 11 item 4): the work per estimate grows with N, the run's with N²;
* ``own ego``: ``truth_now(egos=(vehicle,))`` (what the loop passes now): the
  applying ego's truth and the entities it had in range.

Prints a markdown table of µs per estimate (median of ``--rounds``). The ground
truth per camera instant (``on_truth``) is the loop's, not per estimate.
``python bench/bench_detector.py [--vehicles 1 4 16] [--frames 40] [--rounds 3]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from hil.adapters.wire.messages import Control, DrivingState, Estimate  # noqa: E402
from hil.harness.cases.detector_observer import DetectorObserver  # noqa: E402
from hil.harness.config.detector import DetectorSettings  # noqa: E402
from hil.harness.config.model import CameraConfig  # noqa: E402
from hil import scenarios  # noqa: E402
from hil.scenarios.ground_truth import CameraTruth, RefStateRules  # noqa: E402
from hil.scenarios.sim import Simulation  # noqa: E402
from hil.scenarios.world import CameraSpec  # noqa: E402
from hil.timing.records import FrameStatus, PipelineRecord  # noqa: E402


class _Null:
    def write_json(self, *a: object, **k: object) -> bool:
        return True


def per_estimate_us(n: int, *, frames: int, own_ego: bool) -> float:
    sdef = scenarios.get("multi_vehicle")
    world = sdef.build(params=sdef.resolve({"n_vehicles": n}), seed=1, physics_step_s=0.002, camera=CameraSpec())
    spent = 0
    count = 0
    with Simulation(world, rules=RefStateRules()) as sim:
        egos = list(sim.egos)
        obs = DetectorObserver(DetectorSettings(), egos, camera=CameraConfig(), recorder=_Null(), timing=None)

        def truth_all():  # type: ignore[no-untyped-def]
            return sim.truth_snapshot()

        def truth_own(*, egos=None):  # type: ignore[no-untyped-def]
            return sim.truth_snapshot(egos=egos)

        truth_now = truth_own if own_ego else truth_all
        for f in range(frames):
            for _ in range(50):
                sim.step()
            gt = sim.ground_truth()
            obs.on_truth(gt, t_ns=f)
            for e in gt.egos:
                obs.on_camera_truth(e.vehicle, f, CameraTruth(e.vehicle, gt.sim_time_ns, (), e))
            for _ in range(5):  # controls apply 10 ms later
                sim.step()
            for i, name in enumerate(egos):
                est = Estimate(i, f, DrivingState.SAFE, Control(), (), 0, 0, 0, 0)
                rec = PipelineRecord(name, f, gt.sim_time_ns, 0, 0, FrameStatus.OK, 0, 0, 0, 0, 1, 2,
                                     sim.sim_time_ns)
                t = time.perf_counter_ns()
                obs.on_apply(name, f, truth_now)
                obs.on_record(name, rec, est)
                spent += time.perf_counter_ns() - t
                count += 1
    return spent / count / 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vehicles", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    print("| vehicles | all egos µs/estimate | own ego µs/estimate |")
    print("| --- | --- | --- |")
    for n in a.vehicles:
        res = {own: statistics.median(per_estimate_us(n, frames=a.frames, own_ego=own) for _ in range(a.rounds))
               for own in (False, True)}
        print(f"| {n} | {res[False]:.0f} | {res[True]:.0f} |")
    print(f"\nload average: {open('/proc/loadavg').read().split()[:3]}")


if __name__ == "__main__":
    main()
