"""``hil train``: reproduce the CNN target's shipped weights from scratch.

    hil train                       # dataset seed 0, writes targets/weights/
    hil train --out /tmp/w --data /tmp/cnn-data   # keep (and reuse) the dataset

Steps, all seeded (``--seed``, default 0): generate the dataset with the simulator
(``harness.dataset``: train and validation splits), train the detector and the
steering net on the training split with a fixed seed, deterministic algorithms and
``--threads`` CPU threads (default 2), evaluate both on the validation split, and
write ``detector.pt``, ``steering.pt``, ``metrics.json`` and ``MODEL_CARD.md``.
With the same seed, thread count and machine the weights come out the same; the
metrics say how long each step took.

Metrics (``evaluate_detector``): AP50 is the area under the all-point interpolated
precision-recall curve (PASCAL VOC 2010+) at IoU >= 0.5 per class, averaged over the
classes present. A ground-truth box is *evaluated* when it is at least
``EVAL_MIN_HEIGHT_PX`` = 8 px tall in the 320 x 240 frame (a car ~36 m away) and at
least ``EVAL_MIN_VISIBLE`` = 30 % visible; smaller or mostly hidden ones are
*ignored*: a detection matching one is neither a hit nor a false positive (as
KITTI's difficulty levels do). Steering error is the absolute difference from the
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

EVAL_MIN_HEIGHT_PX = 8.0
EVAL_MIN_VISIBLE = 0.3
TRAIN_MIN_VISIBLE_PX = 4
IOU_MATCH = 0.5
STEER_SCALE = 10.0  # loss units per rad
DEFAULTS = {"train_frames": 3000, "val_frames": 500, "det_epochs": 30, "steer_epochs": 20, "batch": 32}


@dataclass(frozen=True)
class Prepared:
    """A split as the nets see it: uint8 inputs, detector target maps, labels."""

    det: Any           # torch uint8 N x 3 x 120 x 160
    det_maps: Any      # torch float32 N x 8 x 30 x 40 (heat x3, log w, log h, off x, off y, mask)
    steer: Any         # torch uint8 N x 3 x 66 x 200
    steer_label: Any   # torch float32 N (rad)
    samples: list[Any]  # harness.dataset.Sample


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
    from targets.cnn.models import CLASSES, STRIDE
    from targets.cnn.preprocess import DET_H, DET_W

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
    """Decode and preprocess ``samples`` (JPEG as the wire carries it)."""
    import torch

    from targets.cnn.preprocess import detector_input, steering_input

    det, maps, steer, labels = [], [], [], []
    for s in samples:
        bgr = cv2.imdecode(np.frombuffer(s.jpeg, np.uint8), cv2.IMREAD_COLOR)
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
    """CenterNet's focal loss on the heatmaps + L1 on log size and offset at centres."""
    import torch
    from torch.nn import functional as F

    nc = 3
    heat = maps[:, :nc]
    logit = out[:, :nc]
    p = torch.sigmoid(logit).clamp(1e-4, 1 - 1e-4)
    pos = heat.eq(1.0).float()
    neg_w = torch.pow(1 - heat, 4)
    pos_loss = -(torch.log(p) * torch.pow(1 - p, 2) * pos).sum()
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
            total += float(loss) * len(idx)
        losses.append(total / n)
        log(f"{name}: epoch {epoch + 1}/{epochs} loss {losses[-1]:.4f} ({time.perf_counter() - t0:.0f} s)")
    model.eval()
    return losses


def train_detector(data: Prepared, *, epochs: int, batch: int, seed: int, log: Any) -> tuple[Any, list[float]]:
    import torch

    from targets.cnn.models import Detector

    torch.manual_seed(seed)
    model = Detector()

    def batch_fn(idx: Any, gen: Any) -> Any:
        x = data.det[idx]
        maps = data.det_maps[idx]
        flip = torch.rand(len(idx), generator=gen) < 0.5
        if flip.any():
            x = x.clone()
            maps = maps.clone()
            x[flip] = x[flip].flip(-1)
            maps[flip] = torch.stack([_flip_maps(m) for m in maps[flip]])
        return detector_loss(model(_jitter(x, gen)), maps)

    return model, _loop(model, len(data.det), batch_fn, epochs=epochs, batch=batch, lr=4e-3, seed=seed + 1,
                        log=log, name="detector")


def train_steering(data: Prepared, *, epochs: int, batch: int, seed: int, log: Any) -> tuple[Any, list[float]]:
    import torch
    from torch.nn import functional as F

    from targets.cnn.models import SteeringNet

    torch.manual_seed(seed)
    model = SteeringNet()
    with torch.no_grad():
        model.fc[-1].bias[1].fill_(math.log(0.01))

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


def average_precision(dets: list[list[tuple[str, float, tuple[float, ...]]]], gts: list[Sequence[Any]], *,
                      min_height_px: float = EVAL_MIN_HEIGHT_PX,
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
                    if used[j] and evaluated[j]:
                        continue
                    iou = _iou(box, g.box_px)
                    if iou >= best:
                        best, best_j = iou, j
                if best_j < 0:
                    scored.append((conf, False))
                elif evaluated[best_j]:
                    used[best_j] = True
                    scored.append((conf, True))
                # matched an ignored box: neither hit nor false positive
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
               threshold: float = 0.05) -> list[list[tuple[str, float, tuple[float, ...]]]]:
    """Decoded detections (class name, confidence, box in frame px) of every input."""
    import torch

    from targets.cnn.models import CLASSES, decode
    from targets.cnn.preprocess import DET_H, DET_W

    sx, sy = frame_w / DET_W, frame_h / DET_H
    out = []
    with torch.inference_mode():
        for i in range(0, len(det_inputs), 64):
            for o in model(det_inputs[i:i + 64].float()):
                out.append([(CLASSES[d.cls], d.confidence, (d.box[0] * sx, d.box[1] * sy, d.box[2] * sx,
                                                            d.box[3] * sy)) for d in decode(o, threshold=threshold)])
    return out


def evaluate_detector(model: Any, data: Prepared) -> dict[str, Any]:
    """AP50 (module docstring) at three size floors: 8 px (the headline), 16 px, 4 px."""
    dets = detect_all(model, data.det)
    gts = [s.boxes for s in data.samples]
    res = average_precision(dets, gts)
    res["by_min_height"] = {str(h): average_precision(dets, gts, min_height_px=h)["map50"] for h in (4.0, 16.0)}
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
