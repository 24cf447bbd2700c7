"""Does a long run stay bounded in memory? RSS of the harness's processes sampled
through one long real run, and its slope (MB/min) fitted from minute 1 to the end.

    .venv/bin/python bench/bench_soak.py [--minutes 10] [--config hil_configs/demo.yaml]

The run is ``hil run CONFIG --set duration_s=60*minutes`` with corner cases on (the
default), sampled every 5 s: the run process (links, recording, analysis) and, as a
second column, the physics and render processes together. Goal (issue 14): run
process slope <= 0.2 MB/min over a 10-minute run. Floor: the same sampling of an
idle Python process that imports the harness (what the sampler itself sees move).

Each row is also extrapolated to a day (issue 26): RSS at the run's end plus its
slope times the minutes left to 24 h. Below the table, from the run folder: the MCAP
chunks written and the chunk indexes the recorder kept on disk instead of in memory
(``run.mcap`` metadata ``recorder``), and the per-frame blocks that could not be
spilled to ``$TMPDIR`` (``summary.json`` ``spill``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, ValueError, IndexError):
                continue
    return out


def slope(ts: list[float], ys: list[float], *, from_s: float = 60.0, to_s: float = float("inf")) -> float:
    t = np.array(ts)
    y = np.array(ys)
    keep = (t >= from_s) & (t <= to_s)
    if keep.sum() < 3:
        return float("nan")
    return float(np.polyfit(t[keep] / 60.0, y[keep], 1)[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--config", default="hil_configs/demo.yaml")
    a = ap.parse_args()
    load = open("/proc/loadavg").read().split()[0]
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "run"
        p = subprocess.Popen([str(ROOT / ".venv/bin/hil"), "run", a.config, "--no-progress", "--out", str(out),
                              "--set", f"duration_s={a.minutes * 60:g}"], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        # The floor, sampled beside it: an idle process that imports what the run process does.
        idle = subprocess.Popen([sys.executable, "-c", "import time, hil.harness.run.driver; "
                                 f"time.sleep({a.minutes * 60 + 120:g})"], cwd=ROOT)
        t0 = time.monotonic()
        ts, run_mb, eng_mb, idle_mb = [], [], [], []
        while p.poll() is None:
            r = rss_mb(p.pid)
            kids = [k for k in children(p.pid) if b"hil.harness.engine" in Path(f"/proc/{k}/cmdline").read_bytes()
                    or b"multiprocessing" in Path(f"/proc/{k}/cmdline").read_bytes()]
            e = sum(x for k in kids if (x := rss_mb(k)) is not None)
            if r is not None:
                ts.append(time.monotonic() - t0)
                run_mb.append(r)
                eng_mb.append(e)
                idle_mb.append(rss_mb(idle.pid) or float("nan"))
            time.sleep(5)
        idle.kill()
        idle.wait()
        err = p.stderr.read() if p.stderr else ""
        if p.returncode not in (0, 1):
            print(err[-2000:], file=sys.stderr)
            return 1
        kept = run_folder_figures(out)
    print(f"run of {a.minutes:g} min ({a.config}), load before {load}, after "
          f"{open('/proc/loadavg').read().split()[0]}, {os.cpu_count()} cores\n")
    print("| process | RSS at 1 min MB | RSS at the run's end MB | slope MB/min (1 min .. end) | RSS at 24 h MB "
          "(extrapolated) | goal |")
    print("|---|---:|---:|---:|---:|---|")
    # The run's own span: start-up and the first minute out, and the end-of-run work
    # (cutting case windows, the report) after the duration is not part of the slope.
    end_s = a.minutes * 60
    i1 = next((i for i, t in enumerate(ts) if t >= 60), 0)
    ie = max((i for i, t in enumerate(ts) if t <= end_s), default=len(ts) - 1)
    s_run, s_eng = slope(ts, run_mb, to_s=end_s), slope(ts, eng_mb, to_s=end_s)
    s_idle = slope(ts, idle_mb, to_s=end_s)
    left_min = 24 * 60 - a.minutes
    met = "met" if s_run <= 0.2 else "NOT met" if s_run == s_run else "not measured"
    for name, ys, s, goal in (("run process", run_mb, s_run, f"{met} (<= 0.2 MB/min)"),
                              ("physics + render", eng_mb, s_eng, "-"),
                              ("floor: an idle process importing the harness", idle_mb, s_idle, "-")):
        day = ys[ie] + s * left_min if s == s else float("nan")  # NaN: too few samples
        print(f"| {name} | {ys[i1]:.1f} | {ys[ie]:.1f} | {s:+.3f} | "
              f"{'not measured' if day != day else f'{day:.0f}'} | {goal} |")
    print()
    for line in kept:
        print(line)
    return 0


def run_folder_figures(out: Path) -> list[str]:
    """What the run folder says about bounded memory (module docstring), as lines."""
    import json

    from mcap.reader import make_reader

    lines = []
    try:
        with open(out / "run.mcap", "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            rec = next((m.metadata for m in reader.iter_metadata() if m.name == "recorder"), {})
        chunks = summary.statistics.chunk_count if summary is not None and summary.statistics else None
        lines.append(f"MCAP chunks written: {chunks if chunks is not None else 'not measured'}; chunk indexes kept on "
                     f"disk until close: {rec.get('chunk_indexes_spilled', 'not measured')}")
    except (OSError, ValueError, StopIteration) as err:
        lines.append(f"MCAP chunks: not measured ({err})")
    try:
        spill = json.loads((out / "summary.json").read_text()).get("spill")
        lines.append(f"per-frame blocks not spilled to $TMPDIR: "
                     f"{spill['failures'] if spill is not None else 'not measured'}"
                     + (f" ({spill.get('error')})" if spill and spill.get("failures") else ""))
    except (OSError, ValueError) as err:
        lines.append(f"per-frame spill: not measured ({err})")
    return lines


if __name__ == "__main__":
    raise SystemExit(main())
