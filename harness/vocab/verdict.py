"""What a run's figures say to the person who ran it: did the AI meet its budget, did
the harness keep real time, what broke.

The verdict is a pure function of ``summary.json``'s figures (so ``hil report``, the
pytest plugin and CI outputs can rebuild it from any run folder), one :class:`Check`
per :class:`CheckName`:

* ``realtime`` — the physics kept its pace with no step later than its tolerance, and
  no camera frame left later than its tolerance after its camera instant
  (``realtime.kept_realtime``; lockstep runs have no real time to keep);
* ``deadline`` — frames over a stage budget (``timing.thresholds.deadline_ms``,
  default end to end 100 ms), counted per frame: at most
  ``verdict.deadline_miss_fraction`` of any vehicle's measured frames of any budgeted
  stage may be over;
* ``drop`` — frames that got no estimate within ``target.estimate_timeout_s``: at most
  ``verdict.drop_fraction`` of any vehicle's frames;
* ``collision`` — no collision involving an ego;
* ``mismatch`` — no state mismatch against ground truth (corner cases are named);
* ``anomaly`` — no timing anomaly (those caused by the harness itself are named apart).

``hil run --fail-on NAME,...`` (or ``verdict.fail_on``) makes a failed check a failed
run (exit code :data:`EXIT_VERDICT`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

EXIT_VERDICT = 3  # hil run: the run completed, and a check named by --fail-on failed


class CheckName(str, Enum):
    REALTIME = "realtime"
    DEADLINE = "deadline"
    DROP = "drop"
    COLLISION = "collision"
    MISMATCH = "mismatch"
    ANOMALY = "anomaly"


@dataclass(frozen=True)
class Check:
    """One verdict: ``ok``, and one line a person reads (``headline``) with the figure
    behind it (``measured`` against ``limit``, in ``unit``); ``details`` names what
    failed (vehicles, stages, kinds)."""

    name: CheckName
    ok: bool
    headline: str
    measured: float | None = None
    limit: float | None = None
    unit: str = ""
    details: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name.value, "ok": self.ok, "headline": self.headline, "measured": self.measured,
                "limit": self.limit, "unit": self.unit, "details": dict(self.details)}


def parse_fail_on(text: str | Iterable[str]) -> tuple[CheckName, ...]:
    """``deadline,drop`` (or a list of names) as check names.

    Raises:
        ValueError: an unknown name; the message lists the valid ones.
    """
    names = [n.strip() for n in (text.split(",") if isinstance(text, str) else text) if n.strip()]
    valid = [c.value for c in CheckName]
    out = []
    for n in names:
        if n not in valid:
            raise ValueError(f"unknown verdict {n!r}; valid: {', '.join(valid)}")
        out.append(CheckName(n))
    return tuple(dict.fromkeys(out))


def stage_budgets(values: Mapping[str, Any], deadlines: Mapping[str, float]) -> dict[str, dict[str, Any]]:
    """Per-frame budget figures of one vehicle: for each budgeted stage, how many
    measured frames (``values[stage]``: int64 ns, numpy arrays) are over its budget
    (ms), their fraction and the worst value. A budgeted stage with no values (the
    target gives no stamps for it) has ``frames`` 0 and ``worst_ms`` None."""
    import numpy as np

    out: dict[str, dict[str, Any]] = {}
    for stage, ms in deadlines.items():
        a = np.asarray(values.get(stage, ()), dtype=np.int64)
        over = int(np.count_nonzero(a > int(ms * 1e6)))
        out[stage] = {"budget_ms": float(ms), "frames": int(a.size), "over": over,
                      "fraction": round(over / a.size, 6) if a.size else 0.0,
                      "worst_ms": round(int(a.max()) / 1e6, 3) if a.size else None}
    return out


def checks(summary: Mapping[str, Any], *, deadline_miss_fraction: float = 0.0,
           drop_fraction: float = 0.0) -> list[Check]:
    """Every check of a run from its summary figures, in :class:`CheckName` order."""
    vehicles: Mapping[str, Any] = summary.get("vehicles") or {}
    return [_realtime(summary.get("realtime") or {}), _deadline(vehicles, deadline_miss_fraction),
            _drop(vehicles, drop_fraction), _collision(summary, vehicles), _mismatch(summary, vehicles),
            _anomaly(vehicles)]


def verdict_json(summary: Mapping[str, Any], *, fail_on: Iterable[CheckName] = (),
                 deadline_miss_fraction: float = 0.0, drop_fraction: float = 0.0) -> dict[str, Any]:
    """``summary.json``'s ``verdict``: ``passed`` (every check ok), the names that
    ``failed``, those of them that fail the run (``fail_on``), and every check."""
    cs = checks(summary, deadline_miss_fraction=deadline_miss_fraction, drop_fraction=drop_fraction)
    failed = [c.name.value for c in cs if not c.ok]
    fo = [c.value for c in fail_on]
    return {"passed": not failed, "failed": failed, "fail_on": fo,
            "fails_run": [n for n in failed if n in fo],
            "limits": {"deadline_miss_fraction": deadline_miss_fraction, "drop_fraction": drop_fraction},
            "checks": [c.to_json() for c in cs]}


def verdict_of(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The summary's verdict, or one rebuilt from its figures (a run made before the
    verdict existed, or a summary without one)."""
    v = summary.get("verdict")
    return v if isinstance(v, dict) and "checks" in v else verdict_json(summary)


# -- the checks ------------------------------------------------------------------------


def _realtime(rt: Mapping[str, Any]) -> Check:
    if rt.get("mode") != "realtime":
        return Check(CheckName.REALTIME, True, f"not applicable: {rt.get('mode', 'unknown')} mode waits "
                     "for every answer")
    cam = rt.get("camera") or {}
    lag = list(rt.get("lagging") or [])
    parts = []
    if "physics" in lag:
        parts.append(f"physics ran at {rt.get('achieved_factor')}x of {rt.get('requested_factor')}x with "
                     f"{rt.get('late_steps')} steps over {rt.get('late_tolerance_ms')} ms late "
                     f"(worst {rt.get('max_lateness_ms')} ms)")
    if "camera" in lag:
        parts.append(f"{cam.get('late_frames')} of {cam.get('frames')} camera frames left over "
                     f"{cam.get('tolerance_ms')} ms after their camera instant (worst {cam.get('worst_lag_ms')} ms)")
    if "consumers" in lag:
        behind = rt.get("behind") or {}
        parts.append("fell behind the physics (records lost): "
                     + ", ".join(f"{name} {n}" for name, n in sorted(behind.items())))
    if not parts:
        return Check(CheckName.REALTIME, True, "kept: physics on pace with no late step, every camera frame "
                     "out in time", measured=0.0, limit=0.0, unit="late steps and frames",
                     details={"lagging": []})
    return Check(CheckName.REALTIME, False, "not kept: " + "; ".join(parts),
                 measured=float((rt.get("late_steps") or 0) + (cam.get("late_frames") or 0)
                                + sum((rt.get("behind") or {}).values())), limit=0.0,
                 unit="late steps, frames and lost records", details={"lagging": lag})


def _deadline(vehicles: Mapping[str, Any], allowed: float) -> Check:
    over_total = frames_total = 0
    # ((fraction over, worst / budget), vehicle, stage, budget)
    worst: tuple[tuple[float, float], str, str, float] | None = None
    failing: dict[str, dict[str, Any]] = {}
    unmeasured: list[str] = []
    for name, v in vehicles.items():
        for stage, b in (v.get("budgets") or {}).items():
            if not b.get("frames"):
                unmeasured.append(f"{name} {stage}")
                continue
            over_total += b["over"]
            frames_total += b["frames"]
            # The largest share over budget; among equal shares (none over, often), the
            # frame nearest its budget or furthest past it.
            key = (b["fraction"], (b.get("worst_ms") or 0.0) / b["budget_ms"])
            if worst is None or key > worst[0]:
                worst = (key, name, stage, b["budget_ms"])
            if b["over"] and b["fraction"] > allowed:
                failing.setdefault(name, {})[stage] = b
    if not any("budgets" in v for v in vehicles.values()):
        return Check(CheckName.DEADLINE, True, "not measured: this summary has no per-frame budgets (a run made "
                     "before they were counted)")
    if worst is None:
        return Check(CheckName.DEADLINE, True, "not measured: no frame was answered"
                     + (f" ({', '.join(unmeasured)} unmeasured)" if unmeasured else ""),
                     details={"unmeasured": unmeasured})
    text = "; ".join(f"{name}: {b['over']} of {b['frames']} frames over {b['budget_ms']:g} ms {stage} "
                     f"(worst {b['worst_ms']} ms)" for name, st in failing.items() for stage, b in st.items())
    details = {"vehicles": failing, "unmeasured": unmeasured}
    if failing:
        return Check(CheckName.DEADLINE, False, "missed: " + text, measured=float(over_total),
                     limit=allowed, unit="frames over budget", details=details)
    _, vname, stage, budget = worst
    b = vehicles[vname]["budgets"][stage]
    head = (f"met: {over_total} of {frames_total} frames over budget"
            f" (largest: {vname} {stage} {b['over']} of {b['frames']} over {budget:g} ms, worst {b['worst_ms']} ms)")
    return Check(CheckName.DEADLINE, True, head, measured=float(over_total), limit=allowed,
                 unit="frames over budget", details=details)


def _drop(vehicles: Mapping[str, Any], allowed: float) -> Check:
    dropped = {n: int(v.get("dropped") or 0) for n, v in vehicles.items()}
    frames = {n: int(v.get("frames_accounted") or v.get("frames_sent") or 0) for n, v in vehicles.items()}
    bad = {n: d for n, d in dropped.items() if d and d / max(frames[n], 1) > allowed}
    total, n_frames = sum(dropped.values()), sum(frames.values())
    if bad:
        text = "; ".join(f"{n}: {d} of {frames[n]} frames got no estimate in time" for n, d in bad.items())
        return Check(CheckName.DROP, False, "dropped: " + text, measured=float(total), limit=allowed,
                     unit="frames", details={"vehicles": bad})
    return Check(CheckName.DROP, True, f"none over the limit: {total} of {n_frames} frames dropped",
                 measured=float(total), limit=allowed, unit="frames", details={"vehicles": {}})


def _collision(summary: Mapping[str, Any], vehicles: Mapping[str, Any]) -> Check:
    egos = set(vehicles)
    hits = [c for c in (summary.get("collisions") or []) if {c.get("a"), c.get("b")} & egos]
    if not hits:
        return Check(CheckName.COLLISION, True, "none", measured=0.0, limit=0.0, unit="collisions")
    first = hits[0]
    when = first.get("sim_time_ns")
    at = f" at {when / 1e9:.2f} s" if isinstance(when, (int, float)) else ""
    speed = first.get("closing_speed_mps")
    head = (f"{len(hits)} collision{'s' if len(hits) != 1 else ''}: {first.get('a')} and {first.get('b')}{at}"
            + (f", {speed:.1f} m/s" if isinstance(speed, (int, float)) else ""))
    return Check(CheckName.COLLISION, False, head, measured=float(len(hits)), limit=0.0, unit="collisions",
                 details={"collisions": hits[:10]})


def _mismatch(summary: Mapping[str, Any], vehicles: Mapping[str, Any]) -> Check:
    by: dict[str, int] = {}
    for v in vehicles.values():
        for key, n in (v.get("mismatches") or {}).items():
            by[key] = by.get(key, 0) + int(n)
    cases = (summary.get("corner_cases") or {}).get("written")
    # The run's corner cases of every trigger (mismatches and timing anomalies alike).
    case_text = (f"; {cases} corner case{'s' if cases != 1 else ''} written (of every kind: hil cases lists them)"
                 if cases else "")
    if not by:
        return Check(CheckName.MISMATCH, True, "none: the AI's state agreed with ground truth" + case_text,
                     measured=0.0, limit=0.0, unit="mismatches", details={"corner_cases": cases or 0})
    text = ", ".join(f"{n} {k.replace('/', ' (')})" for k, n in sorted(by.items(), key=lambda kv: -kv[1]))
    return Check(CheckName.MISMATCH, False, f"{sum(by.values())}: {text}{case_text}",
                 measured=float(sum(by.values())), limit=0.0, unit="mismatches",
                 details={"by_kind": by, "corner_cases": cases or 0})


def _anomaly(vehicles: Mapping[str, Any]) -> Check:
    by: dict[str, int] = {}
    harness: dict[str, int] = {}
    for v in vehicles.values():
        for kind, n in (v.get("anomalies") or {}).items():
            by[kind] = by.get(kind, 0) + int(n)
        for kind, n in ((v.get("anomaly_causes") or {}).get("harness") or {}).items():
            harness[kind] = harness.get(kind, 0) + int(n)
    if not by:
        return Check(CheckName.ANOMALY, True, "none", measured=0.0, limit=0.0, unit="anomalies")
    parts = []
    for kind, n in sorted(by.items(), key=lambda kv: -kv[1]):
        h = harness.get(kind, 0)
        parts.append(f"{n} {kind.replace('_', ' ')}" + (f" ({h} caused by the harness)" if h else ""))
    return Check(CheckName.ANOMALY, False, f"{sum(by.values())}: " + ", ".join(parts),
                 measured=float(sum(by.values())), limit=0.0, unit="anomalies",
                 details={"by_kind": by, "harness_caused": harness})


__all__ = ["EXIT_VERDICT", "Check", "CheckName", "checks", "parse_fail_on", "stage_budgets", "verdict_json",
           "verdict_of"]
