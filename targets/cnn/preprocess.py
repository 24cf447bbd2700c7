"""Image preprocessing shared by inference and training (numpy + OpenCV, no torch).

Both nets see the frame the wire carries, decoded to BGR (``hil.adapters.sdk.decode_image``):

* detector: the whole frame resized (area averaging) to ``DET_W`` x ``DET_H`` =
  160 x 120, RGB, uint8 (the net normalises);
* steering: the road below the horizon, from ``STEER_ABOVE_HORIZON_PX`` (8 px at 240
  rows) above the horizon row ``cy - fy tan(pitch)`` down to the bottom row, full
  width, resized to ``STEER_H`` x ``STEER_W`` = 66 x 200 (Bojarski et al.'s input
  size), YUV as in the paper, uint8.

Boxes: the detector works in its own 160 x 120 pixels; ``DET_SCALE`` maps a
320 x 240 frame's pixels to it (other frame sizes scale by their own ratio).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

DET_W, DET_H = 160, 120
STEER_W, STEER_H = 200, 66
STEER_ABOVE_HORIZON_PX = 8.0  # at 240 rows; scaled with the frame height


def detector_input(bgr: np.ndarray) -> np.ndarray:
    """HxWx3 BGR uint8 -> DET_H x DET_W x 3 RGB uint8."""
    small = cv2.resize(bgr, (DET_W, DET_H), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(small, cv2.COLOR_BGR2RGB)


def horizon_row(height: int, cy: float, fy: float, pitch_rad: float) -> float:
    """Image row (continuous, px) of the horizon of a level road."""
    del height
    return cy - fy * math.tan(pitch_rad)


def steering_crop_rows(height: int, cy: float, fy: float, pitch_rad: float) -> tuple[int, int]:
    """(first, end) rows of the steering crop in a frame ``height`` rows tall."""
    top = horizon_row(height, cy, fy, pitch_rad) - STEER_ABOVE_HORIZON_PX * height / 240.0
    top_i = int(min(max(0.0, math.floor(top)), height - 8))
    return top_i, height


def steering_input(bgr: np.ndarray, cy: float, fy: float, pitch_rad: float) -> np.ndarray:
    """HxWx3 BGR uint8 -> STEER_H x STEER_W x 3 YUV uint8 (the road below the horizon)."""
    r0, r1 = steering_crop_rows(bgr.shape[0], cy, fy, pitch_rad)
    crop = cv2.resize(bgr[r0:r1], (STEER_W, STEER_H), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(crop, cv2.COLOR_BGR2YUV)
