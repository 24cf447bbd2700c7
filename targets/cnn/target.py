"""The CNN driving AI: detector + steering CNN + pinhole ranging + the baseline's
rules, served through the target SDK like any user's AI.

    python -m hil.targets.cnn [--detector cnn|cv] [--steering cnn|cv] [--transport ...]
    hil target cnn --transport zenoh --listen tcp/0.0.0.0:7447

Per frame (``CnnTarget.infer``; it sees only what the wire carries):

1. decode the image (``hil.adapters.sdk.decode_image``);
2. steering: the steering CNN on the road crop, or the OpenCV baseline's lane
   keeping (``--steering cv``); a CNN output whose own error estimate is too high
   falls back to the baseline for that frame and slows the car down;
3. detection: the CNN detector (class, confidence, box), each box ranged with the
   pinhole model and the class's size priors (``hil.targets.cnn.geometry``), or the
   baseline's colour-blob vehicles (``--detector cv``); uncertain CNN detections in
   the path make the baseline look too;
4. decision and control (``hil.targets.cnn.decision``): SAFE/SLOW/STOP on the nearest
   object in the driven path with the baseline's thresholds.

Models are chosen by the command line (the run config's ``target.args``) and can be
swapped during a run by a COMMAND over the transport (``hil.targets.cnn.commands``).
Weights come from the package (``targets/weights``); nothing is downloaded.
Inference runs on ``--threads`` torch threads (default 1: one core). The SDK stamps
``t_infer_start``/``t_infer_end`` around ``infer`` (the run's ``inference`` stage);
the target also times its own stages (decode, steering, detector, decision), which
``status`` reports and the target's log prints at exit.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.adapters.messages import Control, DetectedObject, Frame, Inference
from hil.adapters.sdk import decode_image
from hil.common.classes import DETECTABLE
from hil.targets.cnn import commands
from hil.targets.cnn.decision import Policy, decide, in_path, nearest_in_path
from hil.targets.cnn.geometry import estimate_position
from hil.targets.cnn.preprocess import DET_H, DET_W, detector_input, steering_input
from hil.targets.cv_baseline import MAX_STEER_RAD, CvBaseline

_CLASS = dict(enumerate(DETECTABLE))  # heatmap channel -> class
STAGES = ("decode", "steering", "detector", "decision", "total")


@dataclass
class CnnStats:
    """Counters of one session (frames, low-confidence overrides, swaps)."""

    frames: int = 0
    detector_uncertain: int = 0        # an uncertain detection in the path: baseline consulted
    detector_confirmed_by_cv: int = 0  # ... and the baseline saw an in-path vehicle
    steering_low_confidence: int = 0   # steering CNN unsure: baseline steering, slow down
    baseline_runs: int = 0             # frames the OpenCV baseline ran on (fallback or chosen)
    swaps: int = 0
    timings_ns: dict[str, deque[int]] = field(default_factory=lambda: {s: deque(maxlen=4096) for s in STAGES})

    def percentiles_ms(self) -> dict[str, tuple[float, float]]:
        """(p50, p99) ms per stage over the last 4096 frames."""
        return {s: (float(np.percentile(v, 50)) / 1e6, float(np.percentile(v, 99)) / 1e6)
                for s, v in self.timings_ns.items() if v}


class CnnTarget:
    """``infer`` is the function the SDK serves, ``infer_batch`` the one a shared
    target's scheduler serves (``hil.adapters.batching``), ``command`` the COMMAND handler.

    Raises:
        FileNotFoundError, ValueError: missing or unfit weights (``models.load``), or
            an unusable ``device``.
    """

    def __init__(self, *, detector: str = "cnn", steering: str = "cnn", policy: Policy | None = None,
                 cruise_speed_mps: float = 10.0, weights_dir: Path | None = None, device: str = "cpu") -> None:
        """``device``: ``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (``hil.targets.cnn.device``);
        the weights are loaded there and the nets run there."""
        from hil.targets.cnn import models
        from hil.targets.cnn.device import device_name, parse_device

        for slot, name in (("detector", detector), ("steering", steering)):
            if name not in commands.MODELS:
                raise ValueError(f"{slot}: unknown model {name!r}; valid: {', '.join(commands.MODELS)}")
        self.policy = policy or Policy()
        self.baseline = CvBaseline(cruise_speed_mps=cruise_speed_mps)  # fallback, and the rules
        det_path = None if weights_dir is None else weights_dir / models.DETECTOR_FILE
        steer_path = None if weights_dir is None else weights_dir / models.STEERING_FILE
        self.det_net, self.det_meta = models.load("detector", det_path)
        self.steer_net, self.steer_meta = models.load("steering", steer_path)
        self.device = parse_device(device)
        self.device_name = device_name(self.device)
        self.det_net.to(self.device)
        self.steer_net.to(self.device)
        self._torch = models.torch
        self._decode = models.decode
        self._lock = threading.Lock()
        self._active = {"detector": detector, "steering": steering}
        self._last_frame_id: int | None = None
        self.stats = CnnStats()

    # -- models ----------------------------------------------------------------

    @property
    def active(self) -> dict[str, str]:
        with self._lock:
            return dict(self._active)

    def swap(self, slot: str, model: str) -> str:
        """Use ``model`` in ``slot`` from the next frame on; returns the reply text.

        Raises:
            ValueError: unknown slot or model (listing the valid ones).
        """
        if slot not in commands.SLOTS or model not in commands.MODELS:
            raise ValueError(f"cannot swap {slot!r} to {model!r}; slots: {', '.join(commands.SLOTS)}, "
                             f"models: {', '.join(commands.MODELS)}")
        with self._lock:
            old = self._active[slot]
            self._active[slot] = model
            last = self._last_frame_id
            self.stats.swaps += 1
            reply = f"ok detector={self._active['detector']} steering={self._active['steering']} after_frame={last}"
        # The target's log is kept in the run folder (target-<vehicle>.log): the swap is on record.
        print(f"cnn: swap {slot} {old} -> {model} after frame {last}", file=sys.stderr, flush=True)
        return reply

    def command(self, text: str) -> str:
        """Handle one COMMAND text; never raises (an error is the reply)."""
        try:
            cmd = commands.parse(text)
        except commands.CommandError as err:
            return f"error: {err}"
        if isinstance(cmd, commands.Swap):
            return self.swap(cmd.slot, cmd.model)
        return "ok " + self.status()

    def status(self) -> str:
        """One line: active models, counters, per-stage p50/p99 (ms) of ``infer``."""
        s = self.stats
        act = self.active
        with self._lock:  # the infer thread appends to the timings
            pct = s.percentiles_ms()
        times = " ".join(f"{k}_p50_ms={p50:.2f} {k}_p99_ms={p99:.2f}" for k, (p50, p99) in pct.items())
        return (f"detector={act['detector']} steering={act['steering']} frames={s.frames} "
                f"detector_uncertain={s.detector_uncertain} detector_confirmed_by_cv={s.detector_confirmed_by_cv} "
                f"steering_low_confidence={s.steering_low_confidence} baseline_runs={s.baseline_runs} "
                f"swaps={s.swaps} device={self.device} {times}").strip()

    # -- the SDK entry point ---------------------------------------------------------

    def infer(self, frame: Frame) -> Inference:
        """Steer, detect, range, decide for one frame (a batch of one).

        Raises:
            ProtocolError, ValueError: the image bytes do not decode.
        """
        return self.infer_batch([frame])[0]

    def infer_batch(self, frames: Sequence[Frame]) -> list[Inference]:
        """Steer, detect, range, decide for each of ``frames`` (any vehicles), each net
        run once on the whole batch on ``self.device``; one ``Inference`` per frame, in
        order. The stage timings of ``stats`` are those of the batch (per call).

        Raises:
            ProtocolError, ValueError: an image does not decode (the whole batch fails).
        """
        if not frames:
            return []
        t0 = time.perf_counter_ns()
        with self._lock:
            det_name, steer_name = self._active["detector"], self._active["steering"]
            self._last_frame_id = frames[-1].frame_id
        bgrs = [decode_image(f) for f in frames]
        n = len(frames)
        cv_results: list[Inference | None] = [None] * n

        def baseline(i: int) -> Inference:
            got = cv_results[i]
            if got is None:
                got = cv_results[i] = self.baseline.infer(frames[i])
                self.stats.baseline_runs += 1
            return got

        t1 = time.perf_counter_ns()
        steers: list[float] = []
        low_steer = [False] * n
        if steer_name == "cnn":
            out = self._run(self.steer_net, [steering_input(b, f.camera.cy, f.camera.fy, f.camera.pitch_rad)
                                             for b, f in zip(bgrs, frames)])
            for i, (s_out, log_err) in enumerate(out.tolist()):
                steer = float(s_out)
                if math.exp(float(log_err)) > self.policy.steer_error_max_rad:
                    low_steer[i] = True
                    self.stats.steering_low_confidence += 1
                    steer = baseline(i).control.steering_rad
                steers.append(steer)
        else:
            steers = [baseline(i).control.steering_rad for i in range(n)]
        steers = [max(-MAX_STEER_RAD, min(MAX_STEER_RAD, s)) for s in steers]
        t2 = time.perf_counter_ns()
        all_objects: list[list[DetectedObject]] = []
        uncertain_ms: list[float | None] = [None] * n
        if det_name == "cnn":
            maps = self._run(self.det_net, [detector_input(b) for b in bgrs])
            for i, frame in enumerate(frames):
                objects, uncertain = self._boxes(maps[i], frame)
                steer = steers[i]
                uncertain_m = uncertain_ms[i] = nearest_in_path(uncertain, steer, self.policy)
                sure_m = nearest_in_path(objects, steer, self.policy)
                if uncertain_m is not None and (sure_m is None or uncertain_m < sure_m):
                    self.stats.detector_uncertain += 1
                    extra = [o for o in baseline(i).objects if in_path(o, steer, self.policy)
                             and not any(_iou(o.box_px, c.box_px) > 0.3 for c in objects)]
                    if extra:
                        self.stats.detector_confirmed_by_cv += 1
                        objects.extend(extra)
                all_objects.append(objects)
        else:
            all_objects = [list(baseline(i).objects) for i in range(n)]
        t3 = time.perf_counter_ns()
        results: list[Inference] = []
        for i, frame in enumerate(frames):
            objects = all_objects[i]
            dist = nearest_in_path(objects, steers[i], self.policy)
            d = decide(self.baseline, self.policy, distance_m=dist, uncertain_m=uncertain_ms[i],
                       speed_mps=frame.ego_speed_mps, steering_low_confidence=low_steer[i])
            objects.sort(key=lambda o: o.position_m[0])
            results.append(Inference(d.state, Control(steers[i], d.throttle, d.brake), tuple(objects)))
        t4 = time.perf_counter_ns()
        s = self.stats
        with self._lock:
            s.frames += n
            for name, dt in zip(STAGES, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0)):
                s.timings_ns[name].append(dt)
        return results

    def _run(self, net: object, images: list[np.ndarray]) -> object:
        """``net`` on HxWx3 uint8 ``images`` as one N x 3 x H x W batch: uint8 to the
        device (a quarter of the bytes of floats), floats made there; output on the CPU."""
        torch = self._torch
        x = torch.from_numpy(np.ascontiguousarray(np.stack(images).transpose(0, 3, 1, 2)))
        x = x.to(self.device, non_blocking=True).float()
        with torch.inference_mode():
            return net(x).cpu()  # type: ignore[operator]

    def _boxes(self, out: object, frame: Frame) -> tuple[list[DetectedObject], list[DetectedObject]]:
        """(confident, uncertain) detections of one detector output, boxes in frame
        pixels, ranged."""
        sx, sy = frame.width / DET_W, frame.height / DET_H
        sure: list[DetectedObject] = []
        unsure: list[DetectedObject] = []
        for det in self._decode(out, threshold=self.policy.det_uncertain):
            x0, y0, x1, y1 = det.box
            box = (max(0.0, x0 * sx), max(0.0, y0 * sy), min(float(frame.width), x1 * sx),
                   min(float(frame.height), y1 * sy))
            cls = _CLASS[det.cls]
            pos = estimate_position(box, cls, frame.camera, frame.width, frame.height)
            if pos is None:
                continue
            obj = DetectedObject(cls, float(min(1.0, det.confidence)), box, pos)
            (sure if det.confidence >= self.policy.det_confidence else unsure).append(obj)
        return sure, unsure


def _iou(a: Sequence[float], b: Sequence[float]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def main(argv: Sequence[str] | None = None, *, prog: str = "python -m hil.targets.cnn") -> int:
    """Serve the CNN target through the target SDK; 2 when the transport is unusable
    (started by hand rather than by the harness) or the weights are missing."""
    from hil.adapters.sdk import TargetArgumentParser

    p = TargetArgumentParser(prog=prog, description="The two-CNN driving AI served over the target SDK.")
    p.add_argument("--detector", choices=commands.MODELS, default="cnn", help="object detector to start with")
    p.add_argument("--steering", choices=commands.MODELS, default="cnn", help="steering model to start with")
    p.add_argument("--cruise-speed", type=float, default=10.0, help="speed to hold when the lane is clear (m/s)")
    p.add_argument("--det-confidence", type=float, default=Policy.det_confidence,
                   help="report and act on detections at or above this confidence")
    p.add_argument("--det-uncertain", type=float, default=Policy.det_uncertain,
                   help="detections from here up to --det-confidence are uncertain (baseline consulted)")
    p.add_argument("--steer-error-max", type=float, default=None,
                   help="steering CNN's own error estimate (rad) above which it is overridden "
                        "(default: calibrated at training, in the weights' metadata)")
    p.add_argument("--weights", type=Path, default=None, help="folder with detector.pt and steering.pt "
                   "(default: the shipped weights)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: one core)")
    p.add_argument("--name", default="cnn", help="target name reported in HELLO (with @device (its name) added)")
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:N or auto (CUDA when available)")
    g = p.add_argument_group("shared target (one process serves many vehicles, frames batched)")
    g.add_argument("--shared", action="store_true",
                   help="zenoh: serve the keys of each of --vehicles on one session (local: implied when the "
                        "harness starts the target with target.shared: true, ignored otherwise)")
    g.add_argument("--vehicles", default="1", help="zenoh: a count N (vehicles 0..N-1) or ids, e.g. 0,2,3")
    g.add_argument("--batch-window-ms", type=float, default=2.0,
                   help="longest a frame waits for other vehicles' frames before its batch runs (ms)")
    g.add_argument("--max-batch", type=int, default=16, help="most frames per batch")
    g.add_argument("--batch-log", default=None,
                   help="CSV of every frame's batch (default: $HIL_BATCH_LOG, set by the harness)")
    from hil.adapters.sdk import add_transport_args, serve, transport_options
    from hil.common.errors import HilError

    add_transport_args(p)
    a = p.parse_args(argv)
    try:
        import torch

        torch.set_num_threads(max(1, a.threads))
        target = CnnTarget(detector=a.detector, steering=a.steering, cruise_speed_mps=a.cruise_speed,
                           weights_dir=a.weights, policy=Policy(det_confidence=a.det_confidence,
                                                                det_uncertain=a.det_uncertain),
                           device=a.device)
        steer_max = a.steer_error_max or float(target.steer_meta.get("steer_error_max_rad", Policy.steer_error_max_rad))
        target.policy = Policy(det_confidence=a.det_confidence, det_uncertain=a.det_uncertain,
                               steer_error_max_rad=steer_max)
    except (FileNotFoundError, ValueError, ImportError) as err:
        print(f"cnn: {err}", file=sys.stderr)
        return 2
    from hil.targets.cnn.device import hello_name

    name = hello_name(a.name, target.device, detail=target.device_name)
    print(f"cnn: device {target.device} ({target.device_name}), torch threads {torch.get_num_threads()}",
          file=sys.stderr, flush=True)
    from hil.adapters.batching import started_shared

    try:
        # local: shared exactly when the harness started it so (target.shared), whatever
        # --shared says, so one config's args serve both placements; zenoh: --shared.
        if started_shared() if a.transport == "local" else a.shared:
            from hil.adapters.batching import ConfigError, parse_vehicles, serve_batched

            try:
                vehicles = parse_vehicles(a.vehicles)
                if a.batch_window_ms < 0 or a.max_batch < 1:
                    raise ValueError(f"--batch-window-ms {a.batch_window_ms:g} / --max-batch {a.max_batch}: "
                                     "expected a window >= 0 and batches of >= 1")
            except ValueError as err:
                print(f"cnn: {err}", file=sys.stderr)
                return 2
            opts = transport_options(a)
            try:
                serve_batched(target.infer_batch, target_name=name, transport=a.transport, on_command=target.command,
                              window_ns=int(a.batch_window_ms * 1e6), max_batch=a.max_batch, vehicles=vehicles,
                              batch_log=a.batch_log, **opts)
            except ConfigError as err:
                print(f"cnn: {err}", file=sys.stderr)
                return 2
        else:
            serve(target.infer, target_name=name, transport=a.transport, on_command=target.command,
                  **transport_options(a))
    except HilError as err:  # an unusable transport, a port in use: one line
        print(f"cnn: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    finally:
        print(f"cnn: {target.status()}", file=sys.stderr, flush=True)
    return 0
