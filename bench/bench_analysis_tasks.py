"""Where the run process's analysis thread spends its CPU, task by task: one `hil run`
in this process with each task the loop and pumps post to the analysis thread
(``hil.harness.engine.analysis_thread``) timed on that thread's CPU clock, summed by
the task's function.

    python bench/bench_analysis_tasks.py [HIL RUN ARGUMENTS ...]

Without arguments: 16 echo vehicles in lockstep at 10 fps for 6 s
(``hil_configs/scale.yaml``), the run of bench/README's "Where the run-side CPU
goes". Prints a markdown table: per task its calls, CPU µs per call and per frame
(frames: the summary's ``harness_cost.frames``), and its share of the thread. Timing each task
costs ~1 µs of its own; the figures move ±15 % between runs on a shared machine
(run it under ``flock -o /tmp/hil-cpu.lock`` and report the load).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

DEFAULT = ["run", "hil_configs/scale.yaml", "--set", "scenario.params.n_vehicles=16", "--set", "mode=lockstep",
           "--set", "duration_s=6", "--set", "target.command=['{python}', -m, hil.targets.echo]", "--no-progress"]


def _name(fn: Callable[..., Any]) -> str:
    inner = getattr(fn, "func", fn)  # a functools.partial's function
    return getattr(inner, "__qualname__", None) or type(inner).__name__


def _timed_tasks() -> dict[str, list[int]]:
    """Time every task the analysis thread runs from now on: name -> [CPU ns, calls]."""
    from hil.harness.engine import analysis_thread

    acc: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    run = analysis_thread.AnalysisThread._run

    def timed_run(self: Any) -> None:
        get = self._q.get

        def timed_get(timeout: float) -> Any:
            item = get(timeout)
            if item is None:
                return None
            fn, args = item

            def task(*a: Any) -> Any:
                t = time.thread_time_ns()
                try:
                    return fn(*a)
                finally:
                    row = acc[_name(fn)]
                    row[0] += time.thread_time_ns() - t
                    row[1] += 1
            return task, args

        self._q.get = timed_get
        run(self)

    analysis_thread.AnalysisThread._run = timed_run  # type: ignore[method-assign]
    return acc


def main(argv: list[str]) -> int:
    argv = argv or DEFAULT
    if "--out" not in argv:
        out = Path(tempfile.mkdtemp(prefix="hil-bench-analysis-")) / "run"
        argv = [*argv, "--out", str(out)]
    else:
        out = Path(argv[argv.index("--out") + 1])
    acc = _timed_tasks()
    from hil.harness.cli.main import main as hil_main

    load = os.getloadavg()[0]
    rc = hil_main(argv)
    if rc != 0:
        print(f"bench_analysis_tasks: hil run exited {rc}", file=sys.stderr)
        return rc
    summary = json.loads((out / "summary.json").read_text())
    cost = summary.get("harness_cost", {})
    frames = int(cost.get("frames") or 0) or 1
    total = sum(ns for ns, _ in acc.values()) or 1
    print(f"\nanalysis thread by task: {frames} frames, load {load:.2f} at the start; "
          f"the summary's analysis thread: {cost.get('analysis_thread_us_per_frame')} µs/frame\n")
    print("| task | calls | µs per call | µs per frame | share |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, (ns, n) in sorted(acc.items(), key=lambda kv: -kv[1][0]):
        print(f"| {name} | {n:,} | {ns / n / 1e3:,.1f} | {ns / frames / 1e3:,.1f} | {ns / total:.0%} |")
    print(f"| all | {sum(n for _, n in acc.values()):,} | | {total / frames / 1e3:,.1f} | 100% |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
