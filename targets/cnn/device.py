"""The torch device the CNN target runs its nets on: ``--device cpu|cuda|cuda:N|auto``.

``auto`` is CUDA (device 0) when torch sees a CUDA device, else the CPU. The device
and its name (``torch.cuda.get_device_name``; the CPU's model from
``/proc/cpuinfo`` where there is one) go into the target's HELLO name and its log,
so a run's summary says where its AI ran.
"""

from __future__ import annotations

from pathlib import Path

import torch


def parse_device(spec: str) -> torch.device:
    """The device ``spec`` names (``cpu``, ``cuda``, ``cuda:N`` or ``auto``).

    Raises:
        ValueError: a spec that is none of those, or CUDA asked for where torch sees
            no CUDA device (or fewer than N + 1 of them).
    """
    text = spec.strip().lower()
    if text == "auto":
        return torch.device("cuda:0") if torch.cuda.is_available() else torch.device("cpu")
    if text == "cpu":
        return torch.device("cpu")
    if text == "cuda" or text.startswith("cuda:"):
        index_text = text.partition(":")[2] or "0"
        if not index_text.isdigit():
            raise ValueError(f"--device {spec!r}: expected cuda:N with N a device index, e.g. cuda:0")
        index = int(index_text)
        if not torch.cuda.is_available():
            raise ValueError(f"--device {spec!r}: torch sees no CUDA device here "
                             f"(torch {torch.__version__}, CUDA build: {torch.version.cuda or 'no'}); "
                             "use --device cpu or auto")
        if index >= torch.cuda.device_count():
            raise ValueError(f"--device {spec!r}: only {torch.cuda.device_count()} CUDA device(s) here")
        return torch.device(f"cuda:{index}")
    raise ValueError(f"--device {spec!r}: expected cpu, cuda, cuda:N or auto")


def device_name(device: torch.device) -> str:
    """What the device is, e.g. ``NVIDIA H100 80GB HBM3`` or the CPU's model name."""
    if device.type == "cuda":
        return str(torch.cuda.get_device_name(device))
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.partition(":")[2].strip()
    except OSError:
        pass
    return "cpu"


def hello_name(base: str, device: torch.device, *, detail: str = "", limit: int = 64) -> str:
    """``base@device (detail)`` for HELLO (``cnn@cuda:0 (NVIDIA H100 80GB HBM3)``),
    cut to ``limit`` bytes of UTF-8 (HELLO's limit)."""
    text = f"{base}@{device}" + (f" ({detail})" if detail else "")
    return text.encode("utf-8")[:limit].decode("utf-8", "ignore")
