"""The campaign summary (``CAMPAIGN/summary.json``, schema version 1), computed from
``campaign.sqlite``.

Keys: ``campaign`` (id, name, scenario, strategy, seed, dims), ``episodes`` (planned,
ran, by status, missing, complete), ``sim_s``, ``virtual_km``, ``wall_s`` (the
campaign's wall time: the longest shard, shards running side by side; the sessions
of one shard add up), ``episodes_per_min`` and ``km_per_h`` over it, ``cases`` (total,
``by_cause``: perception / latency / timing, ``by_kind``, ``by_severity``,
``episodes_with_cases``), ``regions`` (per searched dimension: five equal bins with
episodes, episodes with a mismatch case, their rate and the mean score; ``hot``: the
bin where mismatch cases are densest; ``case_span``: the range the cases were found
in), ``by_generation``, ``slowest`` and ``most_anomalous`` (five each), ``errors``
(the first ten failed episodes) and ``shards``.

A case's cause is the detector's (``perception``: wrong at t0; ``latency``: right at
t0, wrong when applied); corner cases opened by a timing anomaly count as ``timing``.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

from hil.harness.search.db import CampaignDB
from hil.harness.search.episode import Status

SCHEMA_VERSION = 1
BINS = 5
TOP = 5
CAUSES = ("perception", "latency", "timing")


def case_cause(case: dict[str, Any]) -> str:
    cause = case.get("cause")
    return cause if cause in ("perception", "latency") else "timing"


def episode_class(causes: set[str]) -> str:
    """The one class an episode's dot gets: its most latency-bound cause."""
    for c in ("latency", "perception", "timing"):
        if c in causes:
            return c
    return "none"


def build_summary(db: CampaignDB) -> dict[str, Any]:
    c = db.campaign()
    row = db.campaign_row() or {}
    eps = db.episodes()
    cases = db.cases()
    shards = db.shards()
    by_ep: dict[int, set[str]] = {}
    for k in cases:
        by_ep.setdefault(int(k["episode"]), set()).add(case_cause(k))
    ran = {e["episode"] for e in eps}
    missing = [i for i in range(c.episodes) if i not in ran]
    statuses = Counter(e["status"] for e in eps)
    km = sum(e["virtual_km"] or 0.0 for e in eps)
    wall = _campaign_wall(shards)
    mismatch_eps = {i for i, s in by_ep.items() if s & {"perception", "latency"}}
    out: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "campaign": {"id": c.campaign_id, "name": c.name, "scenario": c.scenario, "seed": c.seed,
                     "strategy": c.strategy.model_dump(mode="json"), "hil_version": row.get("hil_version"),
                     "dims": [{"name": d.name, "lo": d.lo, "hi": d.hi, "unit": d.unit} for d in c.dims]},
        "episodes": {"planned": c.episodes, "ran": len(eps), "by_status": dict(sorted(statuses.items())),
                     "missing": len(missing), "missing_first": missing[:20],
                     "complete": not missing and statuses.get(Status.OK, 0) == c.episodes},
        "sim_s": round(sum(e["sim_s"] or 0.0 for e in eps), 3),
        "virtual_km": round(km, 4),
        "wall_s": round(wall, 3),
        "episodes_per_min": round(len(eps) / wall * 60, 3) if wall > 0 else None,
        "km_per_h": round(km / wall * 3600, 3) if wall > 0 else None,
        "cases": {
            "total": len(cases),
            "by_cause": {cause: sum(1 for k in cases if case_cause(k) == cause) for cause in CAUSES},
            "by_kind": dict(sorted(Counter(str(k["kind"]) for k in cases).items())),
            "by_severity": dict(sorted(Counter(str(k["severity"] or "-") for k in cases).items())),
            "episodes_with_cases": len(by_ep),
            "episodes_with_mismatch_cases": len(mismatch_eps),
        },
        "regions": _regions(c.dims, eps, mismatch_eps),
        "by_generation": _generations(eps, by_ep),
        "slowest": [_brief(e) for e in sorted(eps, key=lambda e: (-(e["wall_s"] or 0.0), e["episode"]))[:TOP]],
        "most_anomalous": [_brief(e) for e in sorted(
            eps, key=lambda e: (-(e["score"] or 0.0), -(e["cases"] or 0), -(e["anomalies"] or 0), e["episode"]))[:TOP]
            if (e["score"] or 0) > 0 or (e["cases"] or 0) > 0 or (e["anomalies"] or 0) > 0],
        "errors": [{"episode": e["episode"], "status": e["status"], "error": e["error"] or e["ended_by"]}
                   for e in eps if e["status"] != Status.OK][:10],
        "shards": [{k: s[k] for k in ("shard", "source", "host", "started", "finished", "wall_s", "episodes")}
                   for s in shards],
    }
    return out


def _campaign_wall(shards: list[dict[str, Any]]) -> float:
    per: dict[str, float] = {}
    for s in shards:
        per[s["shard"]] = per.get(s["shard"], 0.0) + float(s["wall_s"] or 0.0)
    return max(per.values(), default=0.0)


def _brief(e: dict[str, Any]) -> dict[str, Any]:
    return {"episode": e["episode"], "dir": e["dir"], "status": e["status"], "score": e["score"],
            "cases": e["cases"], "anomalies": e["anomalies"], "mismatches": e["mismatches"],
            "min_gap_m": e["min_gap"], "wall_s": e["wall_s"], "sim_s": e["sim_s"], "seed": e["seed"],
            "params": e["params"], "origin": e["origin"]}


def _regions(dims: Any, eps: list[dict[str, Any]], hit: set[int]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    overall = len([e for e in eps if e["episode"] in hit]) / len(eps) if eps else 0.0
    for d in dims:
        width = (d.hi - d.lo) / BINS
        bins = [{"lo": round(d.lo + k * width, 6), "hi": round(d.lo + (k + 1) * width, 6), "episodes": 0,
                 "with_cases": 0, "score_sum": 0.0} for k in range(BINS)]
        values = []
        for e in eps:
            v = e["params"].get(d.name)
            if v is None or not math.isfinite(v):
                continue
            b = bins[min(BINS - 1, max(0, int((v - d.lo) / width)))]
            b["episodes"] += 1
            b["score_sum"] += e["score"] or 0.0
            if e["episode"] in hit:
                b["with_cases"] += 1
                values.append(v)
        for b in bins:
            n = b.pop("episodes")
            s = b.pop("score_sum")
            b["episodes"] = n
            b["rate"] = round(b["with_cases"] / n, 4) if n else None
            b["mean_score"] = round(s / n, 4) if n else None
        rated = [b for b in bins if b["rate"] is not None and b["episodes"] > 0]
        hot = max(rated, key=lambda b: (b["rate"], b["mean_score"] or 0.0), default=None)
        out[d.name] = {
            "unit": d.unit, "bins": bins,
            "hot": None if hot is None or not hot["with_cases"] else {
                "lo": hot["lo"], "hi": hot["hi"], "rate": hot["rate"], "overall_rate": round(overall, 4)},
            "case_span": [round(min(values), 6), round(max(values), 6)] if values else None,
        }
    return out


def _generations(eps: list[dict[str, Any]], by_ep: dict[int, set[str]]) -> list[dict[str, Any]]:
    gens: dict[int, list[dict[str, Any]]] = {}
    for e in eps:
        gens.setdefault(int(e["generation"]), []).append(e)
    out = []
    for g, es in sorted(gens.items()):
        n = len(es)
        with_cases = sum(1 for e in es if by_ep.get(e["episode"], set()) & {"perception", "latency"})
        out.append({"generation": g, "episodes": n, "with_mismatch_cases": with_cases,
                    "rate": round(with_cases / n, 4), "mean_score": round(sum(e["score"] or 0 for e in es) / n, 4),
                    "origins": dict(Counter(e["origin"].split(" ", 1)[0] for e in es))})
    return out


__all__ = ["SCHEMA_VERSION", "build_summary", "case_cause", "episode_class"]
