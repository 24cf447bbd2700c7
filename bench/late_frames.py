"""Where and when a run's frames were late: every frame's stamps from a run folder's
``run.mcap`` (``/<vehicle>/pipeline``) as seconds into the run, and a table of the
frames whose capture (``t_state`` -> ``t_tx``) took longer than ``--over-ms``, by second
of the run, stage (render: ``t_state`` -> ``t0``; capture -> send: ``t0`` -> ``t_tx``),
render worker and vehicle.

    python bench/late_frames.py RUN_FOLDER [--over-ms 50] [--csv FILE]
"""

from __future__ import annotations

import argparse
import collections
import csv
import sys
from pathlib import Path

COLUMNS = ("vehicle", "frame_id", "status", "render_worker", "t_state_s", "render_ms", "capture_to_send_ms",
           "to_estimate_ms", "apply_delay_ms")


def frames(run: Path) -> list[dict[str, object]]:
    """Every frame's stamps (``/<vehicle>/pipeline``, read by ``read_run``) as durations
    and seconds after the run's first camera instant."""
    from hil.harness.record.run_folder import read_run

    rows = [r for recs in read_run(run).pipeline.values() for r in recs]
    start = min((int(r["t_state_ns"]) for r in rows if r.get("t_state_ns")), default=0)

    def ms(a: str, b: str, r: dict[str, object]) -> float | None:
        return (int(r[b]) - int(r[a])) / 1e6 if r.get(a) and r.get(b) else None  # type: ignore[call-overload]

    return [{"vehicle": r["vehicle"], "frame_id": r["frame_id"], "status": r["status"],
             "render_worker": r.get("render_worker"),
             "t_state_s": (int(r["t_state_ns"]) - start) / 1e9 if r.get("t_state_ns") else None,  # type: ignore[call-overload]
             "render_ms": ms("t_state_ns", "t0_ns", r), "capture_to_send_ms": ms("t0_ns", "t_tx_ns", r),
             "to_estimate_ms": ms("t_tx_ns", "t0p_ns", r), "apply_delay_ms": ms("t0p_ns", "t_apply_ns", r)}
            for r in rows]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--over-ms", type=float, default=50.0)
    ap.add_argument("--csv", type=Path)
    a = ap.parse_args()
    if not (a.run / "run.mcap").exists():
        print(f"late_frames: {a.run}: no run.mcap", file=sys.stderr)
        return 2
    rows = frames(a.run)
    if a.csv:
        with open(a.csv, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(rows)
    late = [r for r in rows if (r["render_ms"] or 0) + (r["capture_to_send_ms"] or 0) > a.over_ms]  # type: ignore[operator]
    print(f"{len(rows)} frames, {len(late)} with t_state -> t_tx over {a.over_ms:g} ms")
    by_s = collections.Counter(int(r["t_state_s"]) for r in late if r["t_state_s"] is not None)  # type: ignore[call-overload]
    print("by second of the run:", dict(sorted(by_s.items())))
    for key in ("render_worker", "vehicle"):
        print(f"by {key}:", dict(collections.Counter(r[key] for r in late).most_common(20)))
    stage = collections.Counter("render" if (r["render_ms"] or 0) > (r["capture_to_send_ms"] or 0) else "capture_to_send"
                                for r in late)  # type: ignore[operator]
    print("the larger part:", dict(stage))
    for r in sorted(late, key=lambda r: -((r["render_ms"] or 0) + (r["capture_to_send_ms"] or 0)))[:10]:  # type: ignore[operator]
        print("  ", {k: round(v, 2) if isinstance(v, float) else v for k, v in r.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
