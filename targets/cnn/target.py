"""The CNN driving AI: detector + steering CNN + pinhole ranging + the baseline's
rules, served through the target SDK like any user's AI.

    python -m hil.targets.cnn [--detector cnn|cv] [--steering cnn|cv] [--transport ...]
    hil target cnn --transport zenoh --listen tcp/0.0.0.0:7447

Per batch of frames (``CnnTarget.infer_batch``; ``infer`` is a batch of one; it
sees only what the wire carries), in three parts, each timed:

1. **decode**: the images decoded (``hil.adapters.sdk.decode_image``) and the nets'
   inputs made (``hil.targets.cnn.preprocess``), in this process or on decode
   workers (``--decode-workers``, ``hil.targets.cnn.frontend``), or on the device
   (``--preprocess device``, ``hil.targets.cnn.devprep``);
2. **nets**: the steering CNN on the road crops and the CNN detector on the frames,
   each once per batch (``hil.targets.cnn.accel``: device, precision, CUDA graphs);
3. **post**: detections from the heatmaps (``models.decode_batch``), each box ranged
   with the pinhole model and the class's size priors (``hil.targets.cnn.geometry``);
   a steering output whose own error estimate is too high falls back to the OpenCV
   baseline's lane keeping for that frame and slows the car down; uncertain
   detections in the path make the baseline look too; with ``cv`` in a slot the
   baseline answers for it; then decision and control
   (``hil.targets.cnn.decision``): SAFE/SLOW/STOP on the nearest object in the driven
   path with the baseline's thresholds.

Models are chosen by the command line (the run config's ``target.args``,
``hil.targets.cnn.cli``) and can be swapped during a run by a COMMAND over the
transport (``hil.targets.cnn.commands``). Weights come from the package
(``targets/weights``); nothing is downloaded. The nets run on ``--threads`` torch
threads (default 1: one core). The SDK (or a shared target's scheduler) stamps
``t_infer_start``/``t_infer_end`` around the whole batch (the run's ``inference``
stage), so all three parts lie inside it; ``last_parts_ns`` holds the last batch's
parts for a shared target's batch log, and ``status`` (printed at exit) their
p50/p99.
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
from typing import Any

import numpy as np

from hil.adapters.wire.messages import Control, DetectedObject, Frame, ImageEncoding, Inference
from hil.common.classes import DETECTABLE
from hil.targets.cnn import commands
from hil.targets.cnn.decision import Policy, decide, in_path, nearest_in_path
from hil.targets.cnn.geometry import estimate_position
from hil.targets.cnn.preprocess import DET_H, DET_W
from hil.targets.cv_baseline import MAX_STEER_RAD, CvBaseline

_CLASS = dict(enumerate(DETECTABLE))  # heatmap channel -> class
PARTS = ("decode", "nets", "post")  # a batch's parts, in a shared target's batch log as <part>_ns
STAGES = (*PARTS, "total")
PREPROCESS = ("cpu", "device")


@dataclass(frozen=True)
class Serving:
    """How the target runs a batch (``hil.targets.cnn.cli`` names the options).

    ``decode_workers``: 0 decodes in process, N on N workers of ``decode_pool``
    (``process`` or ``thread``), None is ``auto`` (measured at start, and only
    when ``batched``: a shared target's batches). ``max_batch``: the most frames a
    batch holds (the pool's slots, the CUDA graphs' largest bucket). ``precision``
    and ``cuda_graphs``: ``hil.targets.cnn.accel``. ``preprocess``: ``cpu``
    (OpenCV) or ``device`` (``hil.targets.cnn.devprep``)."""

    decode_workers: int | None = 0
    decode_pool: str = "process"
    max_batch: int = 16
    precision: str = "auto"
    preprocess: str = "cpu"
    cuda_graphs: bool = True
    batched: bool = False


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
                 cruise_speed_mps: float = 10.0, weights_dir: Path | None = None, device: str = "cpu",
                 serving: Serving | None = None) -> None:
        """``device``: ``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (``hil.targets.cnn.device``);
        the weights are loaded there and the nets run there. ``serving``: decode
        workers, precision, preprocessing (default: all in this process, fp32 on the
        CPU). Decode worker processes run until ``close``.

        Raises (besides those above): PoolError: a decode worker did not start."""
        from hil.targets.cnn import models
        from hil.targets.cnn.accel import Nets, parse_precision
        from hil.targets.cnn.device import device_name, parse_device
        from hil.targets.cnn.devprep import DevicePrep, gpu_jpeg_decoder
        from hil.targets.cnn.frontend import Frontend, auto_frontend

        sv = self.serving = serving or Serving()
        if sv.preprocess not in PREPROCESS:
            raise ValueError(f"--preprocess {sv.preprocess!r}: expected {' or '.join(PREPROCESS)}")
        if sv.max_batch < 1:
            raise ValueError(f"--max-batch {sv.max_batch}: expected >= 1")

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
        self.dtype = parse_precision(sv.precision, self.device)
        self.nets = Nets(self.det_net, self.steer_net, device=self.device, dtype=self.dtype,
                         max_batch=sv.max_batch, graphs=sv.cuda_graphs)
        self._decode_batch = models.decode_batch
        self._lock = threading.Lock()
        self._active = {"detector": detector, "steering": steering}
        self._last_frame_id: int | None = None
        self.stats = CnnStats()
        self.last_parts_ns: tuple[int, ...] = (0,) * len(PARTS)
        self.device_prep = DevicePrep(self.device) if sv.preprocess == "device" else None
        self.gpu_decode = gpu_jpeg_decoder(self.device) if sv.preprocess == "device" else None
        if sv.decode_workers is None:
            self.frontend = (auto_frontend(slots=sv.max_batch, kind=sv.decode_pool) if sv.batched
                             else Frontend(0, slots=sv.max_batch))
        else:
            self.frontend = Frontend(sv.decode_workers, kind=sv.decode_pool, slots=sv.max_batch)

    def close(self) -> None:
        """End the decode workers (idempotent); ``infer`` decodes in process afterwards."""
        from hil.targets.cnn.frontend import Frontend

        self.frontend.close()
        self.frontend = Frontend(0, slots=self.serving.max_batch)

    def __enter__(self) -> CnnTarget:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def speed(self) -> dict[str, str]:
        """How batches run: decode placement, preprocessing, precision, CUDA graphs."""
        from hil.targets.cnn.accel import precision_name

        return {"decode": self.frontend.describe(),
                "preprocess": "device" + (" (nvJPEG)" if self.gpu_decode else "") if self.device_prep else "cpu",
                "precision": precision_name(self.dtype), "cuda_graphs": ",".join(self.nets.graphed) or "none"}

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
                f"swaps={s.swaps} device={self.device} "
                + "".join(f"{k}={v.replace(' ', '_')} " for k, v in self.speed().items()) + times).strip()

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
        order. The stage timings of ``stats`` and ``last_parts_ns`` are those of the
        batch (per call). Not to be called from two threads at once.

        Raises:
            ProtocolError, ValueError: an image does not decode (the whole batch fails).
        """
        if not frames:
            return []
        t0 = time.perf_counter_ns()
        with self._lock:
            det_name, steer_name = self._active["detector"], self._active["steering"]
            self._last_frame_id = frames[-1].frame_id
        want = [k for k, m in (("det", det_name), ("steer", steer_name)) if m == "cnn"]
        det_in, steer_in = self._inputs(frames, want) if want else (None, None)
        self.nets.sync()
        t1 = time.perf_counter_ns()
        steer_out = self.nets.steering(steer_in).tolist() if steer_in is not None else None
        maps = self.nets.detector(det_in) if det_in is not None else None
        self.nets.sync()
        t2 = time.perf_counter_ns()
        results = self._post(frames, steer_out, maps)
        t3 = time.perf_counter_ns()
        self.last_parts_ns = (t1 - t0, t2 - t1, t3 - t2)
        s = self.stats
        with self._lock:
            s.frames += len(frames)
            for name, dt in zip(STAGES, (*self.last_parts_ns, t3 - t0)):
                s.timings_ns[name].append(dt)
        return results

    def _inputs(self, frames: Sequence[Frame], want: list[str]) -> tuple[Any, Any]:
        """The nets' inputs ``want`` (``det``, ``steer``): uint8 N x H x W x 3 arrays
        made on the CPU, or float tensors made on the device."""
        from hil.targets.cnn.devprep import crop_rows
        from hil.targets.cnn.pool import frame_layout

        sizes = {(f.width, f.height) for f in frames}
        if self.device_prep is None or len(sizes) != 1:  # mixed sizes: whole frames do not stack
            views = self.frontend.prepare(frames, want)
            return views.get("det"), views.get("steer")
        if self.gpu_decode is not None and all(f.encoding == ImageEncoding.JPEG for f in frames):
            full, order = self.gpu_decode(frames), "rgb"
        else:
            width, height = sizes.pop()
            arr = self.frontend.prepare(frames, ("frame",), frame_layout(width, height))["frame"]
            full, order = self.nets.to_device("frame", arr), "bgr"
        prep = self.device_prep
        return (prep.detector(full, order) if "det" in want else None,
                prep.steering(full, crop_rows(frames), order) if "steer" in want else None)

    def _post(self, frames: Sequence[Frame], steer_out: list[list[float]] | None, maps: Any) -> list[Inference]:
        """Detections, overrides, decisions and control of each frame."""
        n = len(frames)
        cv_results: list[Inference | None] = [None] * n

        def baseline(i: int) -> Inference:
            got = cv_results[i]
            if got is None:
                got = cv_results[i] = self.baseline.infer(frames[i])
                self.stats.baseline_runs += 1
            return got

        steers: list[float] = []
        low_steer = [False] * n
        if steer_out is not None:
            for i, (s_out, log_err) in enumerate(steer_out):
                steer = float(s_out)
                if math.exp(float(log_err)) > self.policy.steer_error_max_rad:
                    low_steer[i] = True
                    self.stats.steering_low_confidence += 1
                    steer = baseline(i).control.steering_rad
                steers.append(steer)
        else:
            steers = [baseline(i).control.steering_rad for i in range(n)]
        steers = [max(-MAX_STEER_RAD, min(MAX_STEER_RAD, s)) for s in steers]
        all_objects: list[list[DetectedObject]] = []
        uncertain_ms: list[float | None] = [None] * n
        if maps is not None:
            for i, (frame, dets) in enumerate(zip(frames, self._decode_batch(maps, threshold=self.policy.det_uncertain))):
                objects, uncertain = self._boxes(dets, frame)
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
        results: list[Inference] = []
        for i, frame in enumerate(frames):
            objects = all_objects[i]
            dist = nearest_in_path(objects, steers[i], self.policy)
            d = decide(self.baseline, self.policy, distance_m=dist, uncertain_m=uncertain_ms[i],
                       speed_mps=frame.ego_speed_mps, steering_low_confidence=low_steer[i])
            objects.sort(key=lambda o: o.position_m[0])
            results.append(Inference(d.state, Control(steers[i], d.throttle, d.brake), tuple(objects)))
        return results

    def _boxes(self, dets: Sequence[Any], frame: Frame) -> tuple[list[DetectedObject], list[DetectedObject]]:
        """(confident, uncertain) detections of one frame (``models.Detection``s in
        detector pixels), boxes in frame pixels, ranged."""
        sx, sy = frame.width / DET_W, frame.height / DET_H
        sure: list[DetectedObject] = []
        unsure: list[DetectedObject] = []
        for det in dets:
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
