"""The campaign report reads as tables: the strategy as rows, each parameter's bins
with counts and rates (the densest marked), episodes and cases linked to what exists."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from hil.harness.search.campaign_page import build_page


def _summary() -> dict[str, Any]:
    return {
        "campaign": {"name": "c1", "id": "abc", "scenario": "stopped_car", "seed": 5,
                     "strategy": {"kind": "cem", "elite_frac": 0.25, "mutate": {"sigma": 0.1}},
                     "dims": [{"name": "gap_m", "lo": 10.0, "hi": 30.0, "unit": "m"}]},
        "episodes": {"planned": 2, "ran": 2, "by_status": {"ok": 2}, "missing": 0, "missing_first": [],
                     "complete": True},
        "sim_s": 4.0, "virtual_km": 0.05, "wall_s": 20.0, "episodes_per_min": 6.0, "km_per_h": 9.0,
        "cases": {"total": 1, "episodes_with_cases": 1, "by_cause": {"perception": 1}, "by_kind": {"mismatch.x": 1}},
        "regions": {"gap_m": {"unit": "m", "case_span": [12.0, 12.0],
                              "hot": {"lo": 10.0, "hi": 20.0, "rate": 1.0, "overall_rate": 0.5},
                              "bins": [{"lo": 10.0, "hi": 20.0, "episodes": 1, "with_cases": 1, "rate": 1.0},
                                       {"lo": 20.0, "hi": 30.0, "episodes": 1, "with_cases": 0, "rate": 0.0}]}},
        "by_generation": [{"generation": 0, "episodes": 2, "with_mismatch_cases": 1, "rate": 0.5, "mean_score": 1.0,
                           "origins": {"random": 2}}],
        "most_anomalous": [], "slowest": [], "errors": [],
    }


def test_campaign_page_is_tables_with_links(tmp_path: Path) -> None:
    (tmp_path / "episodes" / "e00000").mkdir(parents=True)
    (tmp_path / "episodes" / "e00000" / "report.html").write_text("<html></html>")
    (tmp_path / "episodes" / "e00000" / "run.mcap").write_bytes(b"")
    cases = [{"episode": 0, "case_id": 1, "vehicle": "ego0", "sim_time_ns": 1_500_000_000, "kind": "mismatch.x",
              "cause": "perception", "severity": "warning", "summary": "missed car1",
              "mcap_path": "episodes/e00000/run.mcap", "episode_dir": "episodes/e00000"},
             {"episode": 1, "case_id": 1, "vehicle": "ego0", "sim_time_ns": 0, "kind": "mismatch.x",
              "cause": "perception", "severity": "warning", "summary": "s", "mcap_path": "episodes/e00001/run.mcap",
              "episode_dir": "episodes/e00001"}]
    html = build_page(_summary(), [], cases, tmp_path)
    assert "{" not in re.sub(r"<style>.*?</style>", "", html, flags=re.S)  # no raw JSON anywhere
    assert "<th>mutate.sigma</th><td>0.1</td>" in html and "<th>kind</th><td>cem</td>" in html
    assert "4 of" not in html and "2 of 2 ran (ok 2)" in html
    # bins: range with unit, counts, rate, densest marked
    assert "<th>bin (m)</th>" in html and "10 – 20" in html and "100% ★ densest" in html and ">0%<" in html
    # the first episode's report and recording exist: linked; the second's do not: plain text
    assert 'href="episodes/e00000/report.html"' in html and 'href="episodes/e00000/run.mcap"' in html
    assert 'href="episodes/e00001' not in html and "<code>1</code>" in html
