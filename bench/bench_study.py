"""Issue 17 goals: the study's wall time, and the link-fault stage's accuracy.

1. ``hil study hil_configs/study.yaml --vehicles 1 2 4 8`` in both placements, timed
   (goal: under 10 minutes on the 2-core machine), with its largest N.
2. One run with uplink delay ``--delay-ms ± --jitter-ms`` and downlink loss
   ``--loss``: the harness's uplink split against the injected delay (frame by frame,
   from ``/ego0/impairment``) and the lost count against the binomial expectation.

    flock -o /tmp/hil-cpu.lock python bench/bench_study.py [--skip-study] [--duration 8]

Prints the load average before and after each part.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def bench_study(out: Path, duration: float) -> None:
    print(f"study: load before {_load()}")
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "study", "hil_configs/study.yaml", "--vehicles",
                        "1", "2", "4", "8", "--duration", f"{duration:g}", "--out", str(out)], cwd=ROOT)
    wall = time.monotonic() - t0
    doc = json.loads((out / "results.json").read_text())
    print(f"study: {wall / 60:.1f} min for {len(doc['points'])} points (goal < 10 min), exit {p.returncode}, "
          f"load after {_load()}")
    print(f"study: largest N holding: {doc['largest_n_holding']}; floor only: {doc['largest_n_floor_only']}")
    print(f"study: report {out / 'report.md'}")


def bench_impair(out: Path, *, delay_ms: float, jitter_ms: float, loss: float, duration: float) -> None:
    from tests.conftest import read_mcap

    print(f"impair: load before {_load()}")
    subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/demo.yaml", "--out", str(out),
                    "--no-progress", "--set", f"duration_s={duration:g}", "--set", "recording.images=false",
                    "--set", 'target.command=["{python}", "-m", "hil.targets.echo"]',
                    "--set", f"target.impair.uplink.delay_ms={delay_ms:g}",
                    "--set", f"target.impair.uplink.jitter_ms={jitter_ms:g}",
                    "--set", f"target.impair.downlink.loss={loss:g}"], cwd=ROOT, check=False,
                   stdout=subprocess.DEVNULL, env={**os.environ})
    s = json.loads((out / "summary.json").read_text())["vehicles"]["ego0"]
    m = read_mcap(out / "run.mcap")
    inj = {r["frame_id"]: r["delay_ns"] / 1e6 for _, r in m["/ego0/impairment"]
           if r["direction"] == "uplink" and r["kind"] == "frame"}
    organic = sorted((r["t_rx_target_ns"] - r["t_tx_ns"]) / 1e6 - inj[r["frame_id"]]
                     for _, r in m["/ego0/pipeline"] if r["status"] == "ok")
    up = s["splits_ms"]["uplink"]
    inj_sorted = sorted(inj.values())
    med = inj_sorted[len(inj_sorted) // 2]
    org = organic[len(organic) // 2]
    print(f"impair: injected uplink {delay_ms:g} ± {jitter_ms:g} ms: median injected {med:.3f} ms; harness uplink "
          f"split p50 {up['p50_ms']:.3f} ms (uncertainty p50 {up['uncertainty_p50_ms']:.3f} ms) = injected + "
          f"organic {org:.3f} ms; error {up['p50_ms'] - org - med:+.3f} ms")
    c = s["link"]["impairment"]["downlink"]
    n, k = c["messages"], c["lost"]
    sigma = math.sqrt(n * loss * (1 - loss))
    print(f"impair: downlink loss {loss:g}: {k} of {n} lost, expected {n * loss:.1f} ± {sigma:.1f} "
          f"({(k - n * loss) / sigma if sigma else 0:+.2f} sigma); frames dropped by the harness: {s['dropped']}")
    print(f"impair: load after {_load()}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skip-study", action="store_true")
    p.add_argument("--duration", type=float, default=8.0, help="seconds per study point")
    p.add_argument("--delay-ms", type=float, default=20.0)
    p.add_argument("--jitter-ms", type=float, default=2.0)
    p.add_argument("--loss", type=float, default=0.1)
    a = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-study-") as tmp:
        if not a.skip_study:
            bench_study(Path(tmp) / "study", a.duration)
        bench_impair(Path(tmp) / "impair", delay_ms=a.delay_ms, jitter_ms=a.jitter_ms, loss=a.loss, duration=10.0)


if __name__ == "__main__":
    main()
