"""The two nets of the CNN target, in torch, small enough for one CPU core.

Steering: ``SteeringNet`` after Bojarski et al. 2016 ("End to End Learning for
Self-Driving Cars", PilotNet): a fixed normalisation layer, five convolutions
(24, 36, 48 channels 5x5 stride 2; 64, 64 channels 3x3) and fully connected layers
of 100, 50 and 10 units on a 66 x 200 YUV crop of the road. ReLU instead of the
paper's unspecified activation. Two outputs: the steering angle (rad, positive left)
and the log-variance of its error, trained as a Gaussian negative log-likelihood:
the net's own estimate of how far it may be off, which the control software uses
to override a low-confidence output (``hil.targets.cnn.decision``).

Detection: ``Detector``, a single-shot anchor-free detector in the style of
CenterNet (Zhou et al. 2019, "Objects as Points") instead of the paper's SSD
MobileNet v1, sized for training on a 2-core CPU: on the 160 x 120 RGB frame a
stride-32 encoder (conv-BN-ReLU, 16/24/32/48/64 channels; its receptive field
spans the frame) with three upsampling merges back to stride 4 (a 40 x 30 grid), and a 1x1 head with per class (vehicle,
pedestrian, obstacle) a centre heatmap, plus the box's log width and log height
(detector pixels) and the sub-cell offset of its centre. ``decode`` keeps heatmap
peaks (3x3 local maxima) above a threshold, then drops boxes overlapping a better
one by IoU > 0.5 (a large object can peak twice): class, confidence (the peak's
value) and box.

Weights are plain tensors saved with ``torch.save`` and read with
``torch.load(weights_only=True)`` (no pickled code), from ``targets/weights``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

try:
    import torch
    from torch import nn
    from torch.nn import functional as F
except ImportError as err:  # pragma: no cover - depends on the install
    raise ImportError("the CNN target needs torch: pip install -e '.[ai]' -c constraints.txt "
                      "(torch==2.13.0, the CPU build)") from err

from hil.common.classes import DETECTABLE
from hil.targets.cnn.preprocess import DET_H, DET_W, STEER_H, STEER_W

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
DETECTOR_FILE, STEERING_FILE = "detector.pt", "steering.pt"
CLASSES = tuple(c.label for c in DETECTABLE)  # heatmap channel order
STRIDE = 4  # detector pixels per output cell
NMS_IOU = 0.5  # a large object can peak in more than one cell: keep the best box
DET_WIDTHS = (16, 24, 32, 48, 64)
STEER_WIDTHS = (24, 36, 48, 64, 64)


def _cbr(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class Detector(nn.Module):
    """Input: N x 3 x 120 x 160 RGB, 0-255 floats. Output: N x 7 x 30 x 40 raw maps
    (3 heatmap logits, log w, log h, offset x, offset y)."""

    rows: torch.Tensor  # a buffer (register_buffer): nn.Module's attribute lookup types it Tensor | Module

    def __init__(self, widths: tuple[int, ...] = DET_WIDTHS) -> None:
        super().__init__()
        c1, c2, c3, c4, c5 = widths
        self.widths = tuple(widths)
        # A row-coordinate channel: how far below the horizon a box stands says how
        # far away it is, which separates a near obstacle from a far car.
        self.register_buffer("rows", torch.linspace(-1.0, 1.0, DET_H).view(1, 1, DET_H, 1).expand(1, 1, DET_H, DET_W)
                             .clone(), persistent=False)
        self.stem = nn.Sequential(_cbr(4, c1, 2), _cbr(c1, c2, 2), _cbr(c2, c2))  # stride 4
        self.down8 = nn.Sequential(_cbr(c2, c3, 2), _cbr(c3, c3))
        self.down16 = nn.Sequential(_cbr(c3, c4, 2), _cbr(c4, c4))
        self.down32 = nn.Sequential(_cbr(c4, c5, 2), _cbr(c5, c5))
        self.merge16 = _cbr(c4 + c5, c4)
        self.merge8 = _cbr(c3 + c4, c3)
        self.merge4 = _cbr(c2 + c3, 32)
        self.head = nn.Conv2d(32, len(CLASSES) + 4, 1)
        head_bias = self.head.bias
        assert head_bias is not None  # a Conv2d made with its bias
        with torch.no_grad():  # CenterNet's prior: heatmaps start near 0.1 % so the loss starts sane
            head_bias[: len(CLASSES)].fill_(-6.9)

    @staticmethod
    def _up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, size=like.shape[-2:], mode="nearest")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.cat([x * (1 / 127.5) - 1.0, self.rows.expand(x.shape[0], -1, -1, -1)], 1)
        a = self.stem(x)
        b = self.down8(a)
        c = self.down16(b)
        d = self.down32(c)
        c = self.merge16(torch.cat([c, self._up(d, c)], 1))
        b = self.merge8(torch.cat([b, self._up(c, b)], 1))
        a = self.merge4(torch.cat([a, self._up(b, a)], 1))
        out: torch.Tensor = self.head(a)  # nn.Module.__call__ is typed Any
        return out


class SteeringNet(nn.Module):
    """Input: N x 3 x 66 x 200 YUV, 0-255 floats. Output: N x 2 (steering rad,
    log of its expected absolute error in rad)."""

    def __init__(self, widths: tuple[int, ...] = STEER_WIDTHS) -> None:
        super().__init__()
        w1, w2, w3, w4, w5 = widths
        self.widths = tuple(widths)
        self.features = nn.Sequential(
            nn.Conv2d(3, w1, 5, 2), nn.ReLU(inplace=True), nn.Conv2d(w1, w2, 5, 2), nn.ReLU(inplace=True),
            nn.Conv2d(w2, w3, 5, 2), nn.ReLU(inplace=True), nn.Conv2d(w3, w4, 3), nn.ReLU(inplace=True),
            nn.Conv2d(w4, w5, 3), nn.ReLU(inplace=True), nn.Flatten())
        with torch.no_grad():
            n = self.features(torch.zeros(1, 3, STEER_H, STEER_W)).shape[1]
        self.fc = nn.Sequential(nn.Linear(n, 100), nn.ReLU(inplace=True), nn.Linear(100, 50), nn.ReLU(inplace=True),
                                nn.Linear(50, 10), nn.ReLU(inplace=True), nn.Linear(10, 2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.fc(self.features(x * (1 / 127.5) - 1.0))  # nn.Module.__call__ is typed Any
        return out


@dataclass(frozen=True)
class Detection:
    """One decoded detection: class index into ``CLASSES``, confidence in [0, 1] and
    box (x0, y0, x1, y1) in detector pixels."""

    cls: int
    confidence: float
    box: tuple[float, float, float, float]


def decode(out: torch.Tensor, *, threshold: float, top_k: int = 32) -> list[Detection]:
    """Detections of one output (7 x 30 x 40, or 1 x 7 x 30 x 40), best first."""
    return decode_batch(out if out.dim() == 4 else out[None], threshold=threshold, top_k=top_k)[0]


def decode_batch(out: torch.Tensor, *, threshold: float, top_k: int = 32) -> list[list[Detection]]:
    """Detections of each output of a batch (N x 7 x 30 x 40, any dtype, on any
    device), best first: heatmap peaks (3x3 local maxima) at or above ``threshold``
    among the ``top_k`` best, their boxes, then ``nms``. One set of tensor operations
    for the whole batch and one copy to the CPU; per frame only the kept peaks are
    Python objects."""
    out = out.float()
    n, nc = out.shape[0], len(CLASSES)
    heat = torch.sigmoid(out[:, :nc])
    peaks = heat * (_max3x3(heat) == heat)
    gh, gw = heat.shape[-2:]
    cells = gh * gw
    scores, idx = peaks.reshape(n, -1).topk(min(top_k, nc * cells), dim=1)
    cell = idx % cells
    ys, xs = cell // gw, cell % gw
    reg = out[:, nc:].reshape(n, 4, cells).gather(2, cell[:, None, :].expand(n, 4, cell.shape[1]))  # n x 4 x k
    table = torch.stack([(scores >= threshold).float(), scores, (idx // cells).float(), (xs.float() + reg[:, 2]) * STRIDE,
                         (ys.float() + reg[:, 3]) * STRIDE, torch.exp(reg[:, 0]), torch.exp(reg[:, 1])], 2)
    result = []
    for rows in table.cpu().tolist():
        dets = [Detection(int(c), s, (x - ww / 2, y - hh / 2, x + ww / 2, y + hh / 2))
                for keep, s, c, x, y, ww, hh in rows if keep]
        result.append(nms(dets, NMS_IOU))
    return result


def _max3x3(x: torch.Tensor) -> torch.Tensor:
    """``F.max_pool2d(x, 3, 1, 1)``, exactly (a maximum is a maximum), as two passes of
    three shifted views: torch 2.13's stride-1 max pooling on the CPU was the slowest
    step of post-processing a batch (``bench/README.md``, bench_shared.py)."""
    p = F.pad(x, (1, 1, 1, 1), value=float("-inf"))
    r = torch.maximum(torch.maximum(p[..., :, :-2], p[..., :, 1:-1]), p[..., :, 2:])
    return torch.maximum(torch.maximum(r[..., :-2, :], r[..., 1:-1, :]), r[..., 2:, :])


def _iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def nms(dets: list[Detection], iou: float) -> list[Detection]:
    """Drop every detection overlapping a more confident one by more than ``iou``
    (any class: one object, one answer). ``dets`` best first."""
    kept: list[Detection] = []
    for d in dets:
        if all(_iou(d.box, k.box) <= iou for k in kept):
            kept.append(d)
    return kept


def fold_batchnorm(model: nn.Module) -> nn.Module:
    """Fold every Conv2d + BatchNorm2d pair of ``model`` (in eval mode) into the
    convolution, in place; returns the model. Same outputs, fewer operations. A
    BatchNorm2d without running statistics (it normalizes by each batch's) stays."""
    for mod in model.modules():
        kids = list(mod.named_children())
        for (_, a), (name_b, b) in zip(kids, kids[1:]):
            if (isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d)
                    and b.running_mean is not None and b.running_var is not None):
                scale = b.weight.detach() / torch.sqrt(b.running_var + b.eps)
                bias = b.bias.detach() - b.running_mean * scale
                if a.bias is not None:
                    bias = bias + a.bias.detach() * scale
                a.weight = nn.Parameter(a.weight.detach() * scale[:, None, None, None], requires_grad=False)
                a.bias = nn.Parameter(bias, requires_grad=False)
                setattr(mod, name_b, nn.Identity())
    return model


def save(model: Detector | SteeringNet, path: Path, meta: dict[str, Any]) -> None:
    """Write ``model``'s weights, its widths and ``meta`` (plain data) to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    torch.save({"widths": list(model.widths), "state": state, "meta": meta}, path)


def load(kind: str, path: Path | None = None) -> tuple[nn.Module, dict[str, Any]]:
    """A net ("detector" or "steering") in eval mode, batch norm folded, from ``path``
    (default: the shipped weights). Returns (model, meta).

    Raises:
        FileNotFoundError: no weights at ``path`` (with how to make them).
        ValueError: ``kind`` is neither, or the file is not weights of that net.
    """
    if kind not in ("detector", "steering"):
        raise ValueError(f"unknown model kind {kind!r}; valid: detector, steering")
    path = path or WEIGHTS_DIR / (DETECTOR_FILE if kind == "detector" else STEERING_FILE)
    if not path.is_file():
        raise FileNotFoundError(f"no {kind} weights at {path}; train them with `hil train`")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or "state" not in blob or "widths" not in blob:
        raise ValueError(f"{path} is not a {kind} weights file (expected keys widths, state, meta)")
    net: nn.Module = Detector(tuple(blob["widths"])) if kind == "detector" else SteeringNet(tuple(blob["widths"]))
    try:
        net.load_state_dict(blob["state"])
    except RuntimeError as err:
        raise ValueError(f"{path}: weights do not fit the {kind} net: {err}") from err
    net.eval()
    if kind == "detector":
        fold_batchnorm(net)
    for p in net.parameters():
        p.requires_grad_(False)
    return net, dict(blob.get("meta", {}))


def input_shapes() -> dict[str, tuple[int, int, int]]:
    """C x H x W of each net's input."""
    return {"detector": (3, DET_H, DET_W), "steering": (3, STEER_H, STEER_W)}
