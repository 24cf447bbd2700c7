"""Does the CNN target keep its accuracy on the paths a GPU takes (issue 30)?

    flock -o /tmp/hil-cpu.lock .venv/bin/python bench/bench_precision.py [--frames 500] [--seeds 10] \
        [--variants fp32,bf16,fp16,device,device-bf16]

Each variant is the CNN target's nets with a ``--precision`` and ``--preprocess``:

* ``fp32``: today's (OpenCV preprocessing, float32 nets): the reference, measured
  in the same run;
* ``bf16``, ``fp16``: the nets' weights and activations in that precision
  (``hil.targets.cnn.accel``), outputs read as float32;
* ``device``, ``device-bf16``: the nets' inputs made in torch from whole decoded
  frames (``hil.targets.cnn.devprep``: what ``--preprocess device`` runs on CUDA).

All run here on the CPU: torch's bf16 and fp16 kernels on the CPU are not cuDNN's,
so a GPU's figures may differ slightly; bf16 keeps 8 bits of mantissa (fp16 11), so
it is the harsher test of the two.

Measured per variant: held-out detector mAP50 (the shipped weights' figure is in
``targets/weights/metrics.json``; the same evaluation as
``tests/targets/test_cnn_quality.py``: ``--frames`` frames of the held-out seed),
vehicle AP50 down to 8 px, steering error against the expert (mean and 95th
percentile, mrad); and the closed loop of ``tests/targets/test_cnn_closed_loop.py``:
``stopped_car`` on seeds 0..``--seeds``-1 (15 s each, JPEG frames at 20 fps,
lockstep), counting the drives that end standing 0.5-12 m behind the car.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.scenarios.gl import select_backend

select_backend()

import numpy as np
import torch

from hil.targets.cnn import models
from hil.targets.cnn.accel import PRECISIONS
from hil.targets.cnn.target import Serving
from hil.training import dataset, train

VARIANTS = {"fp32": Serving(precision="fp32"), "bf16": Serving(precision="bf16"), "fp16": Serving(precision="fp16"),
            "device": Serving(precision="fp32", preprocess="device"),
            "device-bf16": Serving(precision="bf16", preprocess="device")}


class _Cast(torch.nn.Module):
    """A net in ``dtype`` that takes and gives float32 (the evaluation's interface)."""

    def __init__(self, net: torch.nn.Module, dtype: torch.dtype) -> None:
        super().__init__()
        self.net, self.dtype = net.to(dtype), dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.to(self.dtype)).float()


def _device_inputs(data: train.Prepared) -> train.Prepared:
    """``data`` with the nets' inputs made by ``DevicePrep`` from the decoded frames."""
    import cv2

    from hil.targets.cnn.devprep import DevicePrep
    from hil.targets.cnn.preprocess import steering_crop_rows

    prep = DevicePrep(torch.device("cpu"))
    det, steer = [], []
    for i in range(0, len(data.samples), 64):
        chunk = data.samples[i:i + 64]
        bgr = np.stack([cv2.imdecode(np.frombuffer(s.jpeg, np.uint8), cv2.IMREAD_COLOR) for s in chunk])
        full = torch.from_numpy(bgr).permute(0, 3, 1, 2)
        crops = [steering_crop_rows(bgr.shape[1], s.camera[3], s.camera[1], s.camera[5])[0] for s in chunk]
        det.append(prep.detector(full).to(torch.uint8))
        steer.append(prep.steering(full, crops).to(torch.uint8))
    return replace(data, det=torch.cat(det), steer=torch.cat(steer))


def heldout(variant: str, data: train.Prepared, dev_data: train.Prepared) -> dict[str, float]:
    sv = VARIANTS[variant]
    dtype = PRECISIONS[sv.precision]
    use = dev_data if sv.preprocess == "device" else data
    det = _Cast(models.load("detector")[0], dtype)
    steer = _Cast(models.load("steering")[0], dtype)
    d = train.evaluate_detector(det, use)
    s = train.evaluate_steering(steer, use)
    return {"map50": d["map50"], "vehicle8": d["by_min_height"]["8.0"]["vehicle"],
            "mae_mrad": s["mae_rad"] * 1e3, "p95_mrad": s["p95_rad"] * 1e3}


def closed_loop(variant: str, seeds: int) -> tuple[int, list[int]]:
    """(stops, the seeds that failed) of ``stopped_car`` for seeds 0..seeds-1."""
    spec = importlib.util.spec_from_file_location("cnn_closed_loop", ROOT / "tests/targets/test_cnn_closed_loop.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    failed = [seed for seed in range(seeds) if not mod.stopped_car(seed, serving=VARIANTS[variant])[0]]
    return seeds - len(failed), failed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=500, help="held-out frames (the quality test's 500)")
    p.add_argument("--seeds", type=int, default=10, help="stopped_car seeds (the closed-loop test's 10)")
    p.add_argument("--variants", default=",".join(VARIANTS), help=f"of {', '.join(VARIANTS)}")
    a = p.parse_args(argv)
    variants = [v.strip() for v in a.variants.split(",") if v.strip()]
    if not variants or not set(variants) <= set(VARIANTS):
        print(f"--variants {a.variants!r}: expected some of {', '.join(VARIANTS)}", file=sys.stderr)
        return 2
    import json

    shipped = json.loads((models.WEIGHTS_DIR / "metrics.json").read_text())
    torch.set_num_threads(2)
    print(f"# bench_precision: {a.frames} held-out frames, stopped_car seeds 0..{a.seeds - 1}; {os.cpu_count()} cores; "
          f"loadavg before {open('/proc/loadavg').read().split()[:3]}; shipped weights: mAP50 "
          f"{shipped['detector']['map50']:.4f}, steering MAE {shipped['steering']['mae_rad'] * 1e3:.2f} mrad "
          f"(metrics.json, training's validation split)", flush=True)
    t0 = time.monotonic()
    data = train.prepare(list(dataset.generate(seed=dataset.HELDOUT_SEED_BASE, n_frames=a.frames, split=0)))
    dev_data = _device_inputs(data) if any(VARIANTS[v].preprocess == "device" for v in variants) else data
    rows = []
    ref: dict[str, Any] | None = None
    for v in variants:
        h = heldout(v, data, dev_data)
        ref = ref or h
        stops, failed = closed_loop(v, a.seeds) if a.seeds else (0, [])
        rows.append(f"| {v} | {h['map50']:.4f} | {h['map50'] - ref['map50']:+.4f} | {h['vehicle8']:.4f} | "
                    f"{h['mae_mrad']:.2f} | {h['p95_mrad']:.2f} | "
                    + (f"{stops}/{a.seeds}" + (f" (failed: {failed})" if failed else "") if a.seeds else "not run")
                    + " |")
        print(rows[-1], flush=True)
    print(f"\n{time.monotonic() - t0:.0f} s; loadavg after {open('/proc/loadavg').read().split()[:3]}\n")
    print("| variant | held-out mAP50 | vs first row | vehicle AP50 (8 px) | steering MAE mrad | steering p95 mrad "
          "| stopped_car stops |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
