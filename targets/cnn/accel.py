"""The two nets on their device, as fast as it allows: precision, pinned host memory,
CUDA graphs, and the nets' inputs made on the device.

* **Precision** (``--precision auto|fp32|fp16|bf16``): the nets' weights and
  activations; outputs are float32 again before anything reads them. ``auto`` is
  fp32 on the CPU (today's numbers, bit for bit) and ``CUDA_AUTO`` on CUDA, chosen
  because the reduced-precision nets kept the shipped accuracy (held-out mAP50 and
  steering error, and closed-loop stops, measured on the CPU: ``bench/README.md``,
  ``bench_precision.py``). bf16 also runs on the CPU (AMX/AVX-512 where there).
* **CUDA only** (never touched on the CPU, so this module imports and runs
  anywhere): the uint8 inputs are copied once into pinned host buffers and from
  there to the device without blocking; ``cudnn.benchmark`` picks kernels for the
  steady shapes; with ``graphs`` each net is captured as a CUDA graph per batch
  bucket (1, 2, 4, ... up to ``max_batch``), a batch padded up to its bucket, so a
  batch is one graph launch per net instead of dozens of kernel launches. A capture
  that fails is reported once and that net runs eagerly.
* **On the device** (``DevicePrep``, ``--preprocess device``): the decoded frames
  go over whole and are resized and colour-converted there (``devprep``).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

import numpy as np
import torch

PRECISIONS = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}
CUDA_AUTO = "fp16"  # held the shipped accuracy in bf16 and fp16 on the CPU (bench/README.md)


def parse_precision(spec: str, device: torch.device) -> torch.dtype:
    """The nets' dtype ``spec`` names on ``device`` (``auto``: fp32 on the CPU,
    ``CUDA_AUTO`` on CUDA).

    Raises:
        ValueError: none of auto, fp32, fp16, bf16.
    """
    text = spec.strip().lower()
    if text == "auto":
        return PRECISIONS[CUDA_AUTO] if device.type == "cuda" else torch.float32
    if text not in PRECISIONS:
        raise ValueError(f"--precision {spec!r}: expected auto, {', '.join(PRECISIONS)}")
    return PRECISIONS[text]


def precision_name(dtype: torch.dtype) -> str:
    return next(k for k, v in PRECISIONS.items() if v == dtype)


def buckets(max_batch: int) -> list[int]:
    """Batch sizes a graph is captured for: powers of two below ``max_batch``, and it."""
    out, b = [], 1
    while b < max_batch:
        out.append(b)
        b *= 2
    return [*out, max_batch]


def bucket_for(n: int, sizes: Sequence[int]) -> int:
    """The smallest of ``sizes`` (ascending) that holds ``n`` frames.

    Raises:
        ValueError: ``n`` above the largest."""
    for b in sizes:
        if b >= n:
            return b
    raise ValueError(f"a batch of {n} above the largest captured ({sizes[-1]})")


class _Graphed:
    """One net captured as a CUDA graph per bucket (static input and output)."""

    def __init__(self, net: torch.nn.Module, shape: tuple[int, int, int], *, dtype: torch.dtype,
                 device: torch.device, sizes: Sequence[int]) -> None:
        self.sizes = list(sizes)
        self.inputs: dict[int, torch.Tensor] = {}
        self.outputs: dict[int, torch.Tensor] = {}
        self.graphs: dict[int, torch.cuda.CUDAGraph] = {}
        side = torch.cuda.Stream(device)
        for b in self.sizes:
            x = torch.zeros((b, *shape), dtype=dtype, device=device)
            side.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(side), torch.no_grad():
                for _ in range(3):  # warm-up outside the capture (cuDNN picks its kernels)
                    net(x)
            torch.cuda.current_stream(device).wait_stream(side)
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g), torch.no_grad():
                y = net(x)
            self.inputs[b], self.outputs[b], self.graphs[b] = x, y, g

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (n x C x H x W, any dtype, on the device) through the graph of its
        bucket; a view of the static output, valid until this bucket runs again."""
        n = x.shape[0]
        b = bucket_for(n, self.sizes)
        self.inputs[b][:n].copy_(x)
        self.graphs[b].replay()
        return self.outputs[b][:n]


class Nets:
    """Both nets on ``device`` in ``dtype``; inputs are uint8 N x H x W x 3 arrays
    (the CPU's preprocessing) or float N x 3 x H x W tensors already on the device
    (``DevicePrep``'s).

    Args:
        graphs: capture CUDA graphs (CUDA only; ignored on the CPU).
        log: where a failed capture is reported (default: stderr).
    """

    def __init__(self, det_net: torch.nn.Module, steer_net: torch.nn.Module, *, device: torch.device,
                 dtype: torch.dtype = torch.float32, max_batch: int = 16, graphs: bool = True,
                 log: Callable[[str], None] | None = None) -> None:
        self.device, self.dtype, self.max_batch = device, dtype, max_batch
        self.cuda = device.type == "cuda"
        self._log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self.det_net = det_net.to(device=device, dtype=dtype)
        self.steer_net = steer_net.to(device=device, dtype=dtype)
        self._pinned: dict[str, torch.Tensor] = {}
        self._run: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {"det": self.det_net, "steer": self.steer_net}
        self.graphed: list[str] = []
        if self.cuda:
            torch.backends.cudnn.benchmark = True  # steady shapes: pick the fastest kernels once
            if graphs:
                self._capture()

    def _capture(self) -> None:
        from hil.targets.cnn.models import input_shapes

        shapes = input_shapes()
        for key, net, kind in (("det", self.det_net, "detector"), ("steer", self.steer_net, "steering")):
            try:
                self._run[key] = _Graphed(net, shapes[kind], dtype=self.dtype, device=self.device,
                                          sizes=buckets(self.max_batch))
                self.graphed.append(kind)
            except RuntimeError as err:  # a capture the driver refuses: this net runs eagerly
                self._log(f"cnn: no CUDA graph for the {kind} ({type(err).__name__}: {err}); it runs eagerly")

    def sync(self) -> None:
        """Wait for the device's queued work (CUDA; nothing on the CPU): a part's time
        is then its own, not the next part's."""
        if self.cuda:
            torch.cuda.synchronize(self.device)

    def to_device(self, key: str, x: np.ndarray) -> torch.Tensor:
        """uint8 N x H x W x 3 -> uint8 N x 3 x H x W on the device, copied once
        (on CUDA through a pinned buffer, without blocking)."""
        if not self.cuda:
            return torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2)))
        n = x.shape[0]
        buf = self._pinned.get(key)
        if buf is None or buf.shape[0] < n or buf.shape[1:] != x.shape[1:]:
            buf = self._pinned[key] = torch.empty((max(n, self.max_batch), *x.shape[1:]), dtype=torch.uint8,
                                                  pin_memory=True)
        buf[:n].numpy()[...] = x  # the previous batch's copy has completed: every batch ends synchronised
        return buf[:n].to(self.device, non_blocking=True).permute(0, 3, 1, 2)

    def _net(self, key: str, x: np.ndarray | torch.Tensor) -> torch.Tensor:
        t = self.to_device(key, x) if isinstance(x, np.ndarray) else x
        with torch.inference_mode():
            return self._run[key](t.to(self.dtype)).float()

    def detector(self, x: np.ndarray | torch.Tensor) -> torch.Tensor:
        """N x 7 x 30 x 40 float32 maps, left on the device (decoded there)."""
        return self._net("det", x)

    def steering(self, x: np.ndarray | torch.Tensor) -> torch.Tensor:
        """N x 2 float32 on the CPU: steering (rad), log of its expected error."""
        return self._net("steer", x).cpu()
