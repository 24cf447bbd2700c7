"""``hil train``: reproduce the CNN target's shipped weights from scratch.

    hil train                       # dataset seed 0, writes targets/weights/
    hil train --out /tmp/w --data /tmp/cnn-data   # keep (and reuse) the dataset

Steps, all seeded (``--seed``, default 0): generate the dataset with the simulator
(``hil.training.dataset``: train and validation splits), train the detector and the
steering net on the training split with a fixed seed, deterministic algorithms and
``--threads`` CPU threads (default 2), evaluate both on the validation split, and
write ``detector.pt``, ``steering.pt``, ``metrics.json`` and ``MODEL_CARD.md``.
With the same seed, thread count and machine the weights come out the same; the
metrics say how long each step took.

Metrics (``evaluate_detector``): AP50 is the area under the all-point interpolated
precision-recall curve (PASCAL VOC 2010+) at IoU >= 0.5 per class, averaged over the
classes present. A ground-truth box is *evaluated* when it is at least
``EVAL_MIN_HEIGHT_PX`` = 16 px tall in the 320 x 240 frame and at least
``EVAL_MIN_VISIBLE`` = 30 % visible: KITTI's "moderate" floor (25 of 375 rows)
scaled to 240 rows; 16 px is a car 18 m away, a pedestrian 23 m, a 0.7 m obstacle
9 m (a car at 10 m/s needs 18.5 m to stop). AP at 8 px and 4 px floors is reported
beside it (``by_min_height``). Smaller or mostly hidden boxes are *ignored*: a
detection that matches no evaluated box but lies mostly inside an ignored one
(intersection over its own area >= 0.5, COCO's rule for crowd regions) is neither a
hit nor a false positive, nor is one lower than the size floor (KITTI's rule for
detections). Evaluated boxes are matched first (IoU >= 0.5, most confident
detection first, each box once). Steering error is the absolute difference from the
expert's label, in rad, on every validation frame.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from hil.common.eta import time_left

EVAL_MIN_HEIGHT_PX = 16.0
EVAL_MIN_VISIBLE = 0.3
TRAIN_MIN_VISIBLE_PX = 4
IOU_MATCH = 0.5
STEER_SCALE = 10.0  # loss units per rad
# Pedestrians and obstacles are fewer (and pedestrians thinner) than vehicles: their
# centres weigh more in the focal loss.
CLASS_POS_WEIGHT = (1.0, 2.0, 1.5)
DEFAULTS = {"train_frames": 3000, "val_frames": 600, "det_epochs": 40, "steer_epochs": 15, "batch": 32}


@dataclass(frozen=True)
class Prepared:
    """A split as the nets see it: uint8 inputs, detector target maps, labels."""

    det: Any           # torch uint8 N x 3 x 120 x 160
    det_maps: Any      # torch float32 N x 8 x 30 x 40 (heat x3, log w, log h, off x, off y, mask)
    steer: Any         # torch uint8 N x 3 x 66 x 200
    steer_label: Any   # torch float32 N (rad)
    samples: list[Any]  # hil.training.dataset.Sample


# -- data ------------------------------------------------------------------------


def _gaussian(heat: np.ndarray, cx: int, cy: int, sx: float, sy: float) -> None:
    gh, gw = heat.shape
    rx, ry = int(math.ceil(3 * sx)), int(math.ceil(3 * sy))
    x0, x1, y0, y1 = max(0, cx - rx), min(gw, cx + rx + 1), max(0, cy - ry), min(gh, cy + ry + 1)
    xs = np.arange(x0, x1) - cx
    ys = np.arange(y0, y1) - cy
    g = np.exp(-(xs[None, :] ** 2) / (2 * sx * sx) - (ys[:, None] ** 2) / (2 * sy * sy))
    np.maximum(heat[y0:y1, x0:x1], g, out=heat[y0:y1, x0:x1])


def detector_maps(boxes: Sequence[Any], frame_w: int, frame_h: int) -> np.ndarray:
    """Target maps (8 x 30 x 40 float32) of one frame's ``LabelBox``es: per class a
    heatmap with an elliptic Gaussian (sigma = 0.54 x box size / 6, at least 0.4
    cells) on each box's centre cell, and at centre cells the log box size
    (detector px), the sub-cell offset of the centre and a mask."""
    from hil.targets.cnn.models import CLASSES, STRIDE
    from hil.targets.cnn.preprocess import DET_H, DET_W

    gw, gh = DET_W // STRIDE, DET_H // STRIDE
    maps = np.zeros((8, gh, gw), np.float32)
    sx_img, sy_img = DET_W / frame_w, DET_H / frame_h
    for b in boxes:
        x0, y0, x1, y1 = b.box_px
        if b.visible_px < TRAIN_MIN_VISIBLE_PX or x1 - x0 < 2 or y1 - y0 < 2:
            continue
        w, h = (x1 - x0) * sx_img, (y1 - y0) * sy_img
        cxg, cyg = (x0 + x1) / 2 * sx_img / STRIDE, (y0 + y1) / 2 * sy_img / STRIDE
        ix, iy = min(gw - 1, int(cxg)), min(gh - 1, int(cyg))
        k = CLASSES.index(b.cls)
        _gaussian(maps[k], ix, iy, max(0.4, 0.54 * w / STRIDE / 6), max(0.4, 0.54 * h / STRIDE / 6))
        maps[k, iy, ix] = 1.0
        maps[3:, iy, ix] = (math.log(max(w, 0.5)), math.log(max(h, 0.5)), cxg - ix, cyg - iy, 1.0)
    return maps


def prepare(samples: list[Any]) -> Prepared:
    """Decode and preprocess ``samples`` (JPEG as the wire carries it).

    Raises:
        ValueError: a sample's JPEG does not decode (a damaged dataset folder).
    """
    import torch

    from hil.targets.cnn.preprocess import detector_input, steering_input

    det, maps, steer, labels = [], [], [], []
    for i, s in enumerate(samples):
        bgr = cv2.imdecode(np.frombuffer(s.jpeg, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"sample {i}: its JPEG ({len(s.jpeg)} bytes) does not decode")
        fx, fy, cx, cy, _, pitch = s.camera
        det.append(detector_input(bgr).transpose(2, 0, 1))
        maps.append(detector_maps(s.boxes, bgr.shape[1], bgr.shape[0]))
        steer.append(steering_input(bgr, cy, fy, pitch).transpose(2, 0, 1))
        labels.append(s.steering_rad)
    return Prepared(torch.from_numpy(np.stack(det)), torch.from_numpy(np.stack(maps)),
                    torch.from_numpy(np.stack(steer)), torch.tensor(labels, dtype=torch.float32), samples)


# -- losses and augmentation ---------------------------------------------------------


def _flip_maps(maps: Any) -> Any:
    out = maps.flip(-1).clone()
    mask = out[7] > 0
    out[5] = (1.0 - out[5]) * mask  # centre offset x, measured from the flipped cell
    return out


def _jitter(x: Any, gen: Any) -> Any:
    """Brightness and contrast jitter of a uint8 batch -> float batch 0-255."""
    import torch

    n = x.shape[0]
    c = torch.empty(n, 1, 1, 1).uniform_(0.8, 1.2, generator=gen)
    b = torch.empty(n, 1, 1, 1).uniform_(-20.0, 20.0, generator=gen)
    return (x.float() * c + b).clamp_(0, 255)


def detector_loss(out: Any, maps: Any) -> Any:
    """CenterNet's focal loss on the heatmaps (positives weighted per class by
    ``CLASS_POS_WEIGHT``) + L1 on log size and offset at centres."""
    import torch
    from torch.nn import functional as F

    nc = 3
    heat = maps[:, :nc]
    logit = out[:, :nc]
    p = torch.sigmoid(logit).clamp(1e-4, 1 - 1e-4)
    pos = heat.eq(1.0).float()
    neg_w = torch.pow(1 - heat, 4)
    cls_w = torch.tensor(CLASS_POS_WEIGHT, dtype=out.dtype).view(1, nc, 1, 1)
    pos_loss = -(torch.log(p) * torch.pow(1 - p, 2) * pos * cls_w).sum()
    neg_loss = -(torch.log(1 - p) * torch.pow(p, 2) * neg_w * (1 - pos)).sum()
    mask = maps[:, 7:8]
    n_pos = mask.sum().clamp(min=1.0)
    reg = (F.l1_loss(out[:, 3:7], maps[:, 3:7], reduction="none") * mask).sum() / n_pos
    return (pos_loss + neg_loss) / n_pos + reg


def _loop(model: Any, n: int, batch_fn: Any, *, epochs: int, batch: int, lr: float, seed: int,
          log: Any, name: str) -> list[float]:
    import torch

    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    steps = epochs * math.ceil(n / batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.15)
    losses = []
    t0 = time.perf_counter()
    model.train()
    for epoch in range(epochs):
        order = torch.randperm(n, generator=gen)
        total = 0.0
        for i in range(0, n, batch):
            idx = order[i:i + batch]
            loss = batch_fn(idx, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(idx)
        losses.append(total / n)
        dt = time.perf_counter() - t0
        log(f"{name}: epoch {epoch + 1}/{epochs} loss {losses[-1]:.4f} ({dt:.0f} s, {time_left(epoch + 1, epochs, dt)})")
    model.eval()
    return losses


def train_detector(data: Prepared, *, epochs: int, batch: int, seed: int, log: Any) -> tuple[Any, list[float]]:
    import torch

    from hil.targets.cnn.models import Detector

    torch.manual_seed(seed)
    # ~25 % faster on CPU. Module.to takes memory_format (its docstring), its overloads omit it.
    model = Detector().to(memory_format=torch.channels_last)  # type: ignore[call-overload]

    def batch_fn(idx: Any, gen: Any) -> Any:
        x = data.det[idx]
        maps = data.det_maps[idx]
        flip = torch.rand(len(idx), generator=gen) < 0.5
        if flip.any():
            x = x.clone()
            maps = maps.clone()
            x[flip] = x[flip].flip(-1)
            maps[flip] = torch.stack([_flip_maps(m) for m in maps[flip]])
        return detector_loss(model(_jitter(x, gen).contiguous(memory_format=torch.channels_last)), maps)

    return model, _loop(model, len(data.det), batch_fn, epochs=epochs, batch=batch, lr=4e-3, seed=seed + 1,
                        log=log, name="detector")


def train_steering(data: Prepared, *, epochs: int, batch: int, seed: int, log: Any) -> tuple[Any, list[float]]:
    import torch
    from torch.nn import functional as F

    from hil.targets.cnn.models import SteeringNet

    torch.manual_seed(seed)
    model = SteeringNet()
    last = model.fc[-1]
    assert isinstance(last, torch.nn.Linear)
    with torch.no_grad():
        last.bias[1].fill_(math.log(0.01))

    def batch_fn(idx: Any, gen: Any) -> Any:
        x = data.steer[idx]
        y = data.steer_label[idx]
        flip = torch.rand(len(idx), generator=gen) < 0.5
        if flip.any():  # a mirrored road needs the mirrored steering
            x = x.clone()
            x[flip] = x[flip].flip(-1)
            y = torch.where(flip, -y, y)
        out = model(_jitter(x, gen))
        pred, log_err = out[:, 0], out[:, 1]
        fit = F.smooth_l1_loss(pred * STEER_SCALE, y * STEER_SCALE, beta=0.1)
        # The second output learns log |error| of the first (a bounded-gradient
        # stand-in for a variance head): the net's own confidence.
        err_target = torch.log((pred.detach() - y).abs() + 1e-4)
        return fit + 0.05 * F.smooth_l1_loss(log_err, err_target)

    return model, _loop(model, len(data.steer), batch_fn, epochs=epochs, batch=batch, lr=2e-3, seed=seed + 2,
                        log=log, name="steering")


# -- evaluation -------------------------------------------------------------------------


def _iou(a: Sequence[float], b: Sequence[float]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def _ioa(det: Sequence[float], region: Sequence[float]) -> float:
    """Intersection over the detection's own area (COCO's rule for crowd regions)."""
    ix = max(0.0, min(det[2], region[2]) - max(det[0], region[0]))
    iy = max(0.0, min(det[3], region[3]) - max(det[1], region[1]))
    area = (det[2] - det[0]) * (det[3] - det[1])
    return ix * iy / area if area > 0 else 0.0


def average_precision(dets: Sequence[Sequence[tuple[str, float, tuple[float, float, float, float]]]],
                      gts: list[Sequence[Any]], *, min_height_px: float = EVAL_MIN_HEIGHT_PX,
                      min_visible: float = EVAL_MIN_VISIBLE) -> dict[str, Any]:
    """AP at IoU 0.5 per class and their mean over classes with evaluated boxes.

    ``dets[i]``: (class name, confidence, box px) of frame i; ``gts[i]``: its
    ``LabelBox``es. See the module docstring for evaluated and ignored boxes.
    """
    per_class: dict[str, Any] = {}
    for cls in ("vehicle", "pedestrian", "obstacle"):
        scored: list[tuple[float, bool]] = []
        n_eval = 0
        for frame_dets, frame_gts in zip(dets, gts):
            boxes = [g for g in frame_gts if g.cls == cls]
            evaluated = [(g.box_px[3] - g.box_px[1]) >= min_height_px and g.visible_fraction >= min_visible
                         for g in boxes]
            n_eval += sum(evaluated)
            used = [False] * len(boxes)
            for _, conf, box in sorted((d for d in frame_dets if d[0] == cls), key=lambda d: -d[1]):
                best, best_j = IOU_MATCH, -1
                for j, g in enumerate(boxes):
                    if used[j] or not evaluated[j]:
                        continue
                    iou = _iou(box, g.box_px)
                    if iou >= best:
                        best, best_j = iou, j
                if best_j >= 0:
                    used[best_j] = True
                    scored.append((conf, True))
                elif box[3] - box[1] >= min_height_px and not any(
                        not e and _ioa(box, g.box_px) >= IOU_MATCH for e, g in zip(evaluated, boxes)):
                    scored.append((conf, False))
                # else: below the size floor, or mostly inside an ignored box: neither
                # a hit nor a false positive
        if n_eval == 0:
            continue
        scored.sort(key=lambda t: -t[0])
        tp = np.cumsum([s[1] for s in scored]) if scored else np.zeros(0)
        fp = np.cumsum([not s[1] for s in scored]) if scored else np.zeros(0)
        recall = tp / n_eval
        precision = tp / np.maximum(tp + fp, 1)
        mrec = np.concatenate([[0.0], recall, [1.0]])
        mpre = np.concatenate([[1.0], precision, [0.0]])
        mpre = np.maximum.accumulate(mpre[::-1])[::-1]
        ap = float(np.sum((mrec[1:] - mrec[:-1]) * mpre[1:]))
        per_class[cls] = {"ap50": round(ap, 4), "evaluated": n_eval,
                          "recall_max": round(float(recall[-1]) if len(recall) else 0.0, 4)}
    mean = float(np.mean([v["ap50"] for v in per_class.values()])) if per_class else 0.0
    return {"map50": round(mean, 4), "classes": per_class, "min_height_px": min_height_px,
            "min_visible": min_visible}


def detect_all(model: Any, det_inputs: Any, frame_w: int = 320, frame_h: int = 240, *,
               threshold: float = 0.05) -> list[list[tuple[str, float, tuple[float, float, float, float]]]]:
    """Decoded detections (class name, confidence, box in frame px) of every input."""
    import torch

    from hil.targets.cnn.models import CLASSES, decode
    from hil.targets.cnn.preprocess import DET_H, DET_W

    sx, sy = frame_w / DET_W, frame_h / DET_H
    out = []
    with torch.inference_mode():
        for i in range(0, len(det_inputs), 64):
            for o in model(det_inputs[i:i + 64].float()):
                out.append([(CLASSES[d.cls], d.confidence, (d.box[0] * sx, d.box[1] * sy, d.box[2] * sx,
                                                            d.box[3] * sy)) for d in decode(o, threshold=threshold)])
    return out


def evaluate_detector(model: Any, data: Prepared) -> dict[str, Any]:
    """AP50 (module docstring) at the headline size floor (16 px), and the mean AP and
    per-class AP at 8 px and 4 px floors."""
    dets = detect_all(model, data.det)
    gts = [s.boxes for s in data.samples]
    res = average_precision(dets, gts)
    res["by_min_height"] = {}
    for h in (8.0, 4.0):
        r = average_precision(dets, gts, min_height_px=h)
        res["by_min_height"][str(h)] = {"map50": r["map50"], **{k: v["ap50"] for k, v in r["classes"].items()}}
    return res


def evaluate_steering(model: Any, data: Prepared) -> dict[str, Any]:
    """Absolute steering error (rad) against the expert, and the predicted sigma."""
    import torch

    with torch.inference_mode():
        out = torch.cat([model(data.steer[i:i + 128].float()) for i in range(0, len(data.steer), 128)])
    err = (out[:, 0] - data.steer_label).abs().numpy()
    sigma = torch.exp(out[:, 1]).numpy()
    centred = np.array([abs(s.lateral_m) < 0.3 and abs(s.heading_err_rad) < 0.03 for s in data.samples])
    return {"mae_rad": round(float(err.mean()), 5), "rmse_rad": round(float(np.sqrt((err ** 2).mean())), 5),
            "p50_rad": round(float(np.percentile(err, 50)), 5), "p95_rad": round(float(np.percentile(err, 95)), 5),
            "mae_near_centre_rad": round(float(err[centred].mean()), 5) if centred.any() else None,
            "label_std_rad": round(float(data.steer_label.std()), 5),
            "sigma_p50_rad": round(float(np.percentile(sigma, 50)), 5),
            "sigma_p99_rad": round(float(np.percentile(sigma, 99)), 5), "frames": len(err)}


# -- the whole reproduction -------------------------------------------------------------


def train_all(out_dir: Path, *, seed: int = 0, data_dir: Path | None = None, threads: int = 2,
              train_frames: int = DEFAULTS["train_frames"], val_frames: int = DEFAULTS["val_frames"],
              det_epochs: int = DEFAULTS["det_epochs"], steer_epochs: int = DEFAULTS["steer_epochs"],
              batch: int = DEFAULTS["batch"], log: Any = print) -> dict[str, Any]:
    """Generate the dataset (or reuse ``data_dir`` when it holds the same one), train
    and evaluate both nets, write weights, ``metrics.json`` and ``MODEL_CARD.md`` to
    ``out_dir``; returns the metrics.

    Raises:
        SimulationError: the simulator cannot render (no GL backend).
        ImportError: torch is not installed.
    """
    import torch

    from hil.targets.cnn import models
    from hil.training import dataset

    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    tmp = None
    if data_dir is None:
        tmp = tempfile.mkdtemp(prefix="hil-train-")
        data_dir = Path(tmp)
    try:
        meta_path = data_dir / "meta.json"
        want = {"train": train_frames, "val": val_frames}
        if meta_path.is_file() and json.loads(meta_path.read_text()).get("seed") == seed \
                and json.loads(meta_path.read_text()).get("frames") == want:
            log(f"dataset: reusing {data_dir}")
            meta = json.loads(meta_path.read_text())
        else:
            log(f"dataset: rendering {train_frames} + {val_frames} frames into {data_dir}")
            meta = dataset.build_dataset(data_dir, seed=seed, n_train=train_frames, n_val=val_frames, log=log)
        timings["dataset_s"] = time.perf_counter() - t
        t = time.perf_counter()
        train_data = prepare(dataset.read_split(data_dir / "train"))
        val_data = prepare(dataset.read_split(data_dir / "val"))
        timings["prepare_s"] = time.perf_counter() - t
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    t = time.perf_counter()
    det, det_losses = train_detector(train_data, epochs=det_epochs, batch=batch, seed=seed, log=log)
    timings["detector_s"] = time.perf_counter() - t
    det_metrics = evaluate_detector(det, val_data)
    log(f"detector: validation mAP50 {det_metrics['map50']:.3f}")
    t = time.perf_counter()
    steer, steer_losses = train_steering(train_data, epochs=steer_epochs, batch=batch, seed=seed, log=log)
    timings["steering_s"] = time.perf_counter() - t
    steer_metrics = evaluate_steering(steer, val_data)
    # Low-confidence threshold: 3x the 99th percentile of the net's own error estimate
    # on validation frames (at least 0.02 rad), so that in-distribution frames keep it.
    steer_max = round(max(0.02, 3.0 * steer_metrics["sigma_p99_rad"]), 4)
    log(f"steering: validation MAE {steer_metrics['mae_rad']:.4f} rad; low-confidence above {steer_max} rad")
    counts = {split: _composition(s.samples) for split, s in (("train", train_data), ("val", val_data))}
    common = {"seed": seed, "threads": threads, "batch": batch, "dataset": meta, "torch": str(torch.__version__)}
    models.save(det, out_dir / models.DETECTOR_FILE, {**common, "epochs": det_epochs, "metrics": det_metrics})
    models.save(steer, out_dir / models.STEERING_FILE, {**common, "epochs": steer_epochs,
                                                         "metrics": steer_metrics, "steer_error_max_rad": steer_max})
    timings = {k: round(v, 1) for k, v in timings.items()}
    metrics = {"detector": det_metrics, "steering": steer_metrics, "steer_error_max_rad": steer_max,
               "losses": {"detector": [round(x, 4) for x in det_losses],
                          "steering": [round(x, 5) for x in steer_losses]},
               "composition": counts, "timings_s": timings, **common,
               "parameters": {"detector": sum(p.numel() for p in det.parameters()),
                              "steering": sum(p.numel() for p in steer.parameters())},
               "epochs": {"detector": det_epochs, "steering": steer_epochs}}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    (out_dir / "MODEL_CARD.md").write_text(model_card(metrics))
    return metrics


def _composition(samples: list[Any]) -> dict[str, Any]:
    by_source: dict[str, int] = {}
    boxes: dict[str, int] = {}
    for s in samples:
        by_source[s.source] = by_source.get(s.source, 0) + 1
        for b in s.boxes:
            if b.box_px[3] - b.box_px[1] >= 8:
                boxes[b.cls] = boxes.get(b.cls, 0) + 1
    return {"frames": len(samples), "by_source": by_source, "boxes_8px_or_taller": boxes}


def _floors(d: dict[str, Any]) -> str:
    parts = []
    for h, r in d["by_min_height"].items():
        per = ", ".join(f"{k} {v:.3f}" for k, v in r.items() if k != "map50")
        parts.append(f"boxes >= {float(h):g} px mAP50 {r['map50']:.3f} ({per})")
    return "; ".join(parts)


def model_card(m: dict[str, Any]) -> str:
    """MODEL_CARD.md text from the metrics of a training run."""
    d, s, c = m["detector"], m["steering"], m["composition"]
    cls_rows = "\n".join(f"| {k} | {v['ap50']:.3f} | {v['evaluated']} | {v['recall_max']:.3f} |"
                         for k, v in d["classes"].items())
    src = ", ".join(f"{k} {v}" for k, v in sorted(c["train"]["by_source"].items()))
    boxes = ", ".join(f"{k} {v}" for k, v in sorted(c["train"]["boxes_8px_or_taller"].items()))
    t = m["timings_s"]
    total = sum(t.values())
    n_det, n_steer = (f"{m['parameters'][k]:,}" for k in ("detector", "steering"))
    ped8 = d["by_min_height"]["8.0"].get("pedestrian", 0.0)
    return f"""# CNN target weights — model card

Written by `hil train` (training/train.py); do not edit by hand: rerun `hil train` to
reproduce the weights and this card (same seed, same thread count, same machine:
same bits). Nothing is downloaded, at training or at run time.

## Models

| file | net | parameters | input | output |
| --- | --- | --- | --- | --- |
| `detector.pt` | CenterNet-style single-shot detector, stride-32 encoder, merges to stride 4 | {n_det} | 160 x 120 RGB (whole frame) + row coordinate | per class heatmap, log box size, centre offset on a 40 x 30 grid |
| `steering.pt` | PilotNet (Bojarski et al. 2016): normalisation, 5 conv, FC 100-50-10 | {n_steer} | 66 x 200 YUV crop of the road below the horizon | steering (rad) and log of its expected error |

## Data

Rendered by the simulator (`training/dataset.py`, seed {m['seed']}): 320 x 240 JPEG frames
(quality 70-95) with labels from ground truth — the visible boxes and classes
(segmentation render) and the steering of an expert doing pure pursuit on the true
lane centre 8 m ahead of the camera. Training {c['train']['frames']} frames ({src});
validation {c['val']['frames']} frames from a different seed stream. Boxes 8 px or
taller in training: {boxes}. Composed worlds have random roads (arcs of radius
60-800 m), static cars of any paint, pedestrians, obstacles; registered scenarios
are driven by the expert with random parameters; poses are perturbed up to +-1.3 m
and +-0.12 rad for recovery labels.

## Training

torch {m['torch']}, {m['threads']} CPU threads, deterministic algorithms, seed
{m['seed']}, batch {m['batch']}, AdamW with a one-cycle schedule; random horizontal flips
(steering label negated) and brightness/contrast jitter. Detector: {m['epochs']['detector']}
epochs, CenterNet focal loss + L1 on log size and offset. Steering: {m['epochs']['steering']} epochs,
smooth L1 on the angle + L1 of the second output on log |error|.

Wall time on the machine that trained them: dataset {t.get('dataset_s', 0):.0f} s, preprocessing
{t.get('prepare_s', 0):.0f} s, detector {t.get('detector_s', 0):.0f} s, steering {t.get('steering_s', 0):.0f} s; total {total / 60:.1f} min.

## Metrics (validation split)

Detector AP at IoU 0.5, evaluated boxes >= {d['min_height_px']:g} px tall and >= {d['min_visible']:.0%} visible
(KITTI's "moderate" floor scaled to 240 rows; smaller or hidden ones ignored;
training/train.py says how): **mAP50 {d['map50']:.3f}**. With lower floors: {_floors(d)}.

| class | AP50 | evaluated boxes | max recall |
| --- | --- | --- | --- |
{cls_rows}

Steering error against the expert over {s['frames']} frames: mean {s['mae_rad'] * 1000:.2f} mrad,
RMS {s['rmse_rad'] * 1000:.2f} mrad, median {s['p50_rad'] * 1000:.2f} mrad, 95th percentile
{s['p95_rad'] * 1000:.2f} mrad (the labels' spread: {s['label_std_rad'] * 1000:.1f} mrad); near the lane centre
(within 0.3 m and 0.03 rad) mean {(s['mae_near_centre_rad'] or 0) * 1000:.2f} mrad. The net's own error
estimate: median {s['sigma_p50_rad'] * 1000:.2f} mrad, 99th percentile {s['sigma_p99_rad'] * 1000:.2f} mrad; the target
overrides a steering output whose estimate exceeds {m['steer_error_max_rad']} rad.

Closed-loop results and inference times are measured by the tests
(`tests/targets/test_cnn_*.py`) and `bench/bench_inference.py`, not here.

## Limits

Trained on this simulator's flat-shaded box vehicles, pedestrians and obstacles, one
camera (60 deg vertical field of view, 1.3 m high, level), daylight without shadows:
it knows nothing else. Obstacles are boxes 0.3-1 m on a side; ranges of obstacles rest
on the ground contact of their box. The weak spot is far pedestrians: 8-16 px tall
(23-45 m away), their dark trousers barely differ from the road, and AP50 for
pedestrians falls to {ped8:.2f} with boxes down to 8 px.
"""


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``hil train``."""
    p = sub.add_parser("train", help="reproduce the CNN target's weights from scratch (seeded)",
                       description="Reproduce the CNN target's weights from scratch: render the dataset, "
                                   "train both nets with a fixed seed, evaluate, write weights and model card.")
    p.add_argument("--seed", type=int, default=0, help="dataset and training seed (the shipped weights: 0)")
    p.add_argument("--out", type=Path, default=None, help="where to write the weights (default: targets/weights)")
    p.add_argument("--data", type=Path, default=None,
                   help="keep the dataset in this folder (and reuse it when it matches); default: a temporary one")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (the shipped weights: 2)")
    p.add_argument("--train-frames", type=int, default=DEFAULTS["train_frames"])
    p.add_argument("--val-frames", type=int, default=DEFAULTS["val_frames"])
    p.add_argument("--det-epochs", type=int, default=DEFAULTS["det_epochs"])
    p.add_argument("--steer-epochs", type=int, default=DEFAULTS["steer_epochs"])


def cmd(args: argparse.Namespace) -> int:
    """Run ``hil train``; 0 on success, 2 when torch or the renderer is missing."""
    from hil.scenarios.gl import select_backend

    try:
        import torch  # noqa: F401
    except ImportError:
        print("hil train: needs torch: pip install -e '.[ai]' -c constraints.txt", file=sys.stderr)
        return 2
    select_backend()
    from hil.targets.cnn.models import WEIGHTS_DIR

    out = args.out or WEIGHTS_DIR
    for name, v in (("--train-frames", args.train_frames), ("--val-frames", args.val_frames),
                    ("--det-epochs", args.det_epochs), ("--steer-epochs", args.steer_epochs),
                    ("--threads", args.threads)):
        if v < 1:
            print(f"hil train: {name} must be at least 1, got {v}", file=sys.stderr)
            return 2
    t0 = time.perf_counter()
    m = train_all(out, seed=args.seed, data_dir=args.data, threads=args.threads, train_frames=args.train_frames,
                  val_frames=args.val_frames, det_epochs=args.det_epochs, steer_epochs=args.steer_epochs,
                  log=lambda text: print(text, flush=True))
    print(f"wrote {out}: detector mAP50 {m['detector']['map50']:.3f}, steering MAE "
          f"{m['steering']['mae_rad'] * 1000:.2f} mrad, in {(time.perf_counter() - t0) / 60:.1f} min")
    return 0
