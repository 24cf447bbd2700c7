"""The nets' inputs made on the device from whole decoded frames (``--preprocess
device``): what ``hil.targets.cnn.preprocess`` does with OpenCV, in torch, so the
frames go to the device once, as decoded, and nothing else is done to them on the
CPU. Runs on any torch device (the CPU too: that is how it is tested and how its
accuracy was measured here).

* Resizing is OpenCV's ``INTER_AREA`` for shrinking, written as two matrix products
  (rows, then columns) whose weights are ``cv::resize``'s area table (each output
  pixel the mean of the input area it covers, partial pixels weighted by the part
  covered), rounded to uint8 values as OpenCV does. A 2x shrink (the detector's)
  gives OpenCV's bytes exactly; the steering crop's fractional one sums in another
  order, so a pixel may differ by one level.
* Colour: the detector's RGB is a channel order; the steering net's YUV is
  OpenCV's 8-bit ``COLOR_BGR2YUV`` in its own fixed-point arithmetic (14-bit
  coefficients), exactly.
* ``gpu_jpeg_decoder``: JPEG frames decoded on the GPU by torchvision's nvJPEG
  decoder (``torchvision.io.decode_jpeg(..., device='cuda')``), when torchvision
  imports beside this torch and the device is CUDA; otherwise None and the frames
  are decoded on the CPU. torchvision is not a dependency: PyPI's torchvision does
  not import beside the CPU-only torch 2.13 this project pins.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

from hil.adapters.wire.messages import Frame, ImageEncoding
from hil.common.errors import ProtocolError
from hil.targets.cnn.preprocess import DET_H, DET_W, STEER_H, STEER_W, steering_crop_rows

# OpenCV's 8-bit RGB -> YUV: Y = (R 4899 + G 9617 + B 1868 + 2^13) >> 14,
# U = ((B - Y) 8061 + (128 << 14) + 2^13) >> 14, V = ((R - Y) 14369 + ...) >> 14.
_SHIFT, _R2Y, _G2Y, _B2Y, _B2U, _R2V = 14, 4899, 9617, 1868, 8061, 14369


def area_weights(n_in: int, n_out: int) -> torch.Tensor:
    """n_out x n_in float64 matrix of OpenCV's ``INTER_AREA`` shrink along one axis
    (``computeResizeAreaTab``: slivers under 1e-3 of a pixel are dropped).

    Raises:
        ValueError: not a shrink (n_out > n_in) or an empty axis."""
    if not 0 < n_out <= n_in:
        raise ValueError(f"area resize {n_in} -> {n_out}: expected 0 < out <= in")
    scale = n_in / n_out
    w = torch.zeros((n_out, n_in), dtype=torch.float64)
    for d in range(n_out):
        f1 = d * scale
        f2 = f1 + scale
        cell = min(scale, n_in - f1)
        s1, s2 = math.ceil(f1), math.floor(f2)
        s2 = min(s2, n_in - 1)
        s1 = min(s1, s2)
        if s1 - f1 > 1e-3:
            w[d, s1 - 1] = (s1 - f1) / cell
        for s in range(s1, s2):
            w[d, s] = 1.0 / cell
        if f2 - s2 > 1e-3:
            w[d, s2] = min(min(f2 - s2, 1.0), cell) / cell
    return w


def _round_u8(x: torch.Tensor) -> torch.Tensor:
    return torch.floor(x + 0.5).clamp_(0, 255)


class DevicePrep:
    """Makes both nets' inputs from uint8 N x 3 x H x W frames on ``device``
    (channel order ``bgr`` from OpenCV, ``rgb`` from nvJPEG); float32 outputs with
    uint8 values, N x 3 x 120 x 160 RGB and N x 3 x 66 x 200 YUV."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self._weights: dict[tuple[int, int], torch.Tensor] = {}

    def _w(self, n_in: int, n_out: int) -> torch.Tensor:
        key = (n_in, n_out)
        w = self._weights.get(key)
        if w is None:
            w = self._weights[key] = area_weights(n_in, n_out).to(self.device, torch.float32)
        return w

    def resize(self, x: torch.Tensor, height: int, width: int) -> torch.Tensor:
        """uint8-valued N x C x h x w -> N x C x ``height`` x ``width`` (area shrink)."""
        h, w = x.shape[-2:]
        y = torch.matmul(self._w(h, height), x.float())
        return _round_u8(torch.matmul(y, self._w(w, width).T))

    def detector(self, frames: torch.Tensor, order: str = "bgr") -> torch.Tensor:
        rgb = frames.flip(1) if order == "bgr" else frames
        return self.resize(rgb, DET_H, DET_W)

    def steering(self, frames: torch.Tensor, crops: Sequence[int], order: str = "bgr") -> torch.Tensor:
        """``crops``: each frame's first row of the road crop (``steering_crop_rows``)."""
        out = torch.empty((frames.shape[0], 3, STEER_H, STEER_W), dtype=torch.float32, device=frames.device)
        for top in sorted(set(crops)):  # one camera, one crop: usually a single group
            idx = [i for i, c in enumerate(crops) if c == top]
            sel = frames[idx] if len(idx) < frames.shape[0] else frames
            out[idx] = yuv(self.resize(sel[:, :, top:], STEER_H, STEER_W), order)
        return out


def yuv(x: torch.Tensor, order: str = "bgr") -> torch.Tensor:
    """uint8-valued N x 3 x H x W (``order``) -> YUV as OpenCV's 8-bit conversion."""
    c = x.to(torch.int32)
    b, g, r = (c[:, 0], c[:, 1], c[:, 2]) if order == "bgr" else (c[:, 2], c[:, 1], c[:, 0])
    half = 1 << (_SHIFT - 1)
    y = (r * _R2Y + g * _G2Y + b * _B2Y + half) >> _SHIFT
    u = ((b - y) * _B2U + (128 << _SHIFT) + half) >> _SHIFT
    v = ((r - y) * _R2V + (128 << _SHIFT) + half) >> _SHIFT
    return torch.stack([y, u, v], 1).clamp_(0, 255).float()


def crop_rows(frames: Sequence[Frame]) -> list[int]:
    """Each frame's first steering-crop row."""
    return [steering_crop_rows(f.height, f.camera.cy, f.camera.fy, f.camera.pitch_rad)[0] for f in frames]


def gpu_jpeg_decoder(device: torch.device) -> Callable[[Sequence[Frame]], torch.Tensor] | None:
    """A batch decoder of JPEG frames on the GPU (N x 3 x H x W RGB uint8 on
    ``device``), or None: not CUDA, or torchvision does not import here."""
    if device.type != "cuda":
        return None
    try:  # torchvision: on GPU hosts only (not a dependency), so mypy may or may not find it
        from torchvision.io import ImageReadMode, decode_jpeg  # type: ignore[import-not-found, unused-ignore]
    except Exception:  # noqa: BLE001 - ImportError, or torchvision built for another torch (RuntimeError)
        return None

    def decode(frames: Sequence[Frame]) -> torch.Tensor:
        if any(f.encoding != ImageEncoding.JPEG for f in frames):
            raise ValueError("the GPU decoder takes JPEG frames only")
        data = [torch.frombuffer(bytearray(f.data), dtype=torch.uint8) for f in frames]
        try:
            images = decode_jpeg(data, mode=ImageReadMode.RGB, device=device)
        except RuntimeError as err:
            raise ProtocolError(f"JPEG image does not decode on the GPU: {err}", offset=0) from err
        for f, img in zip(frames, images):
            if tuple(img.shape[1:]) != (f.height, f.width):
                raise ProtocolError("JPEG image does not decode to the frame's size", offset=0)
        return torch.stack(images)

    return decode
