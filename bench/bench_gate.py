"""How often does ``hil compare`` pass an unchanged build, and fail a real regression?

Records a pool of short lockstep runs of ``hil_configs/regression.yaml`` (the CI
gate's own config): ``--runs`` of the unchanged build (the OpenCV baseline target)
and as many of a regressed one (the same target with ``--delay-ms`` slept inside
every inference: ``bench/slow_cv_target.py``), interleaved base, slow, base, slow...
so that changes of the machine's load hit both alike. Then it draws ``--pairs``
comparisons of each kind from the pool (seeded):

* unchanged: BASE = base run i, RUN = base run j (i != j) -> must pass;
* regressed: BASE = base run i, RUN = slow run j -> must fail;

and judges each pair with the gate (``hil.harness.check.gate``: bootstrap of the per-frame
samples in run.mcap, default tolerances and alpha) and, for contrast, with the old
point comparison of the two summaries (``--point``). It prints the pass counts, the
checks that failed and how often, the size of the injected regression as measured
(median over the pool of each run's end-to-end p50/p99), and the load average
before and after. Goal (issue 12): unchanged passes >= 19 of 20, regressed fails >=
19 of 20.

    flock -o /tmp/hil-cpu.lock .venv/bin/python bench/bench_gate.py            # record + judge (~3-6 min)
    .venv/bin/python bench/bench_gate.py --pool /tmp/gate-pool --reuse         # judge a recorded pool again

Runs already recorded in the pool (with a summary.json) are kept: remove the pool
for a fresh one. Options: ``--pool DIR`` (default /tmp/hil-gate-pool), ``--reuse``
(judge the runs already in the pool, record nothing), ``--runs 10``, ``--duration-s 8`` (simulated seconds per run:
160 frames at 20 fps), ``--delay-ms 2``, ``--pairs 20``, ``--seed 1``.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CONFIG = ROOT / "hil_configs" / "regression.yaml"


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def record(pool: Path, *, runs: int, duration_s: float, delay_ms: float) -> None:
    """Record ``runs`` base and ``runs`` slow runs into ``pool``, interleaved."""
    from hil.scenarios.gl import select_backend

    backend = select_backend()
    from hil.harness.config.loading import load_config
    from hil.harness.run.driver import execute, prepare_out_dir

    from hil.common.errors import HilError

    slow_cmd = [sys.executable, str(ROOT / "bench" / "slow_cv_target.py"), "--delay-ms", f"{delay_ms:g}"]
    pool.mkdir(parents=True, exist_ok=True)
    for i in range(runs):
        for kind in ("base", "slow"):
            out = pool / f"{kind}-{i:02d}"
            if (out / "summary.json").is_file():  # recorded by an earlier call: kept
                continue
            overrides = [f"duration_s={duration_s:g}", "progress=false"]
            cfg = load_config(CONFIG, overrides=overrides)
            if kind == "slow":
                cfg = cfg.model_copy(update={"target": cfg.target.model_copy(update={"command": slow_cmd})})
            t = time.perf_counter()
            for attempt in range(3):  # a target that fails to start is tried again, twice
                shutil.rmtree(out, ignore_errors=True)
                try:
                    res = execute(cfg, out_dir=prepare_out_dir(out), gl_backend=backend,
                                  install_signal_handlers=False)
                    break
                except HilError as err:
                    print(f"  {kind}-{i:02d} attempt {attempt + 1} failed: {err}", flush=True)
                    time.sleep(10)
            else:
                raise SystemExit(f"{out}: could not record it")
            e2e = res.summary["vehicles"]["ego0"]["latency_ms"]["end_to_end"]
            print(f"  recorded {kind}-{i:02d}: {time.perf_counter() - t:5.1f} s, e2e p50 {e2e['p50_ms']:.2f} "
                  f"p99 {e2e['p99_ms']:.2f} ms, ended by {res.summary['ended_by']}, load {_loadavg()}", flush=True)


def judge(pool: Path, *, pairs: int, seed: int) -> None:
    from hil.harness.record.run_folder import load_summary
    from hil.harness.check.gate import GateSettings, compare, load_run

    base = sorted(p for p in pool.glob("base-*") if (p / "summary.json").is_file())
    slow = sorted(p for p in pool.glob("slow-*") if (p / "summary.json").is_file())
    if len(base) < 2 or not slow:
        raise SystemExit(f"{pool}: needs at least 2 base runs and 1 slow run (record them first)")
    rng = random.Random(seed)
    same = [(a, b) for a in base for b in base if a != b]
    worse = [(a, b) for a in base for b in slow]
    draws = {"unchanged": rng.sample(same, min(pairs, len(same))),
             "regressed": rng.sample(worse, min(pairs, len(worse)))}
    loaded = {p: load_run(p) for p in base + slow}
    settings = GateSettings()
    print(f"\npool {pool}: {len(base)} base + {len(slow)} slow runs; load average {_loadavg()}\n")
    for name, runs in (("base", base), ("slow", slow)):
        s = [load_summary(p)["vehicles"]["ego0"]["latency_ms"]["end_to_end"] for p in runs]
        print(f"{name}: end_to_end p50 median {statistics.median(x['p50_ms'] for x in s):.2f} ms "
              f"(range {min(x['p50_ms'] for x in s):.2f}-{max(x['p50_ms'] for x in s):.2f}), "
              f"p99 median {statistics.median(x['p99_ms'] for x in s):.2f} ms "
              f"(range {min(x['p99_ms'] for x in s):.2f}-{max(x['p99_ms'] for x in s):.2f})")
    _noise_table([loaded[p][1] for p in base])
    print("\n| comparison | pairs | gate (bootstrap) passes | gate fails | old point gate passes | "
          "checks that failed (gate) | checks that failed (old) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    t_judge = time.perf_counter()
    n_judged = 0
    for name, ps in draws.items():
        passes = old_passes = 0
        why: Counter[str] = Counter()
        why_old: Counter[str] = Counter()
        for a, b in ps:
            (sa, xa), (sb, xb) = loaded[a], loaded[b]
            checks = compare(sa, sb, base_samples=xa, run_samples=xb, settings=settings)
            n_judged += 1
            failed = [c for c in checks if c.verdict.fails]
            passes += not failed
            why.update(f"{c.stage} {c.metric}".replace("- ", "") for c in failed)
            old = [c for c in compare(sa, sb) if c.verdict.fails]
            old_passes += not old
            why_old.update(f"{c.stage} {c.metric}".replace("- ", "") for c in old)
        fmt = (lambda c: ", ".join(f"{k} x{n}" for k, n in c.most_common(5)) or "-")
        print(f"| {name} | {len(ps)} | {passes} | {len(ps) - passes} | {old_passes} | {fmt(why)} | {fmt(why_old)} |")
    per = (time.perf_counter() - t_judge) / max(n_judged, 1)
    print(f"\n(each line judged with the default tolerances, alpha {settings.alpha:g} over all checks, "
          f"{settings.resamples} block resamples; {per * 1e3:.0f} ms per comparison incl. the point gate; "
          f"load average now {_loadavg()})")


def _noise_table(runs: list) -> None:
    """Between-run spread of each stage's figures over the base runs: what the gate's
    ``noise`` defaults stand for (hil.harness.check.gate_tolerances)."""
    import numpy as np

    from hil.timing.gate import Metric

    vs = [r.vehicles["ego0"] for r in runs if "ego0" in r.vehicles]
    metrics = ("p1", "p50", "p99", "std")
    print("\nrun-to-run spread of the unchanged build (sd over the base runs, ms and % of the mean):\n")
    print("| stage | " + " | ".join(metrics) + " |")
    print("| --- |" + " --- |" * len(metrics))
    for stage in vs[0].stages_ms if vs else ():
        cells = []
        for m in metrics:
            v = np.array([Metric(m).of(x.stages_ms[stage]) for x in vs if x.stages_ms.get(stage) is not None
                          and x.stages_ms[stage].size])
            sd = float(v.std(ddof=1)) if v.size > 1 else float("nan")
            cells.append(f"{sd:.2f} ({sd / v.mean() * 100:.0f} %)" if v.size > 1 and v.mean() else "-")
        print(f"| {stage} | " + " | ".join(cells) + " |")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pool", type=Path, default=Path("/tmp/hil-gate-pool"))
    p.add_argument("--reuse", action="store_true", help="judge the runs already in --pool")
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--duration-s", type=float, default=8.0)
    p.add_argument("--delay-ms", type=float, default=2.0)
    p.add_argument("--pairs", type=int, default=20)
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args()
    print(f"bench_gate: load average {_loadavg()}, {os.cpu_count()} cores", flush=True)
    if not a.reuse:
        record(a.pool, runs=a.runs, duration_s=a.duration_s, delay_ms=a.delay_ms)
    judge(a.pool, pairs=a.pairs, seed=a.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
