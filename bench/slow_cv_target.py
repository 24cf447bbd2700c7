"""The OpenCV baseline target with an injected delay: the known regression that
``bench_gate.py`` must catch.

    python bench/slow_cv_target.py --delay-ms 2 [cv_baseline options]

Each frame's inference sleeps ``--delay-ms`` after the baseline's own work (inside
the target's inference stamps, as a slower model would), so end-to-end, to_apply,
target_total and inference all grow by about that much (plus the sleep's own
oversleep, ~0.1 ms).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.adapters.wire.messages import Frame, Inference  # noqa: E402
from hil.targets import cv_baseline  # noqa: E402


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench/slow_cv_target.py", add_help=False)
    p.add_argument("--delay-ms", type=float, default=2.0, help="sleep per frame inside inference (ms)")
    a, rest = p.parse_known_args(argv)
    delay_s = a.delay_ms / 1e3
    infer = cv_baseline.CvBaseline.infer

    def slower(self: cv_baseline.CvBaseline, frame: Frame) -> Inference:
        out = infer(self, frame)
        time.sleep(delay_s)
        return out

    cv_baseline.CvBaseline.infer = slower  # type: ignore[method-assign]
    return cv_baseline.main(rest)


if __name__ == "__main__":
    raise SystemExit(main())
