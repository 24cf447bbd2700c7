"""hil study (harness/study/study.py, harness/study/study_page.py): bad input is one line and
exit 2 before any run; the largest-N rule; a tiny real study (N = 1, 2; 2 s runs) in
both placements writes its table, plots and a report that opens with its reading."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.harness.study.study_page import largest_holding, write_study
from hil.harness.study.study import Placement, Point, PointResult
from tests.conftest import GL_BACKEND, ahead_folder, ahead_results, beside
from tests.harness.browser import assert_charts_legible, needs_chromium, probe

ROOT = Path(__file__).resolve().parents[3]


def _hil(*argv: str, timeout: float = 60, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *argv], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.mark.parametrize(("argv", "needle"), [
    (["hil_configs/study.yaml", "--vehicles", "0", "2"], "--vehicles"),
    (["hil_configs/demo.yaml"], "n_vehicles"),
    (["hil_configs/study.yaml", "--set", "camera.fps=-1"], "camera.fps"),
    (["hil_configs/remote.yaml", "--placement", "distributed"], "n_vehicles"),
])
def test_bad_input_is_one_line_and_exit_2_before_any_run(tmp_path, argv, needle):
    p = _hil("study", *argv, "--out", str(tmp_path / "s"))
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert needle in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "s").exists()


def test_a_folder_holding_anything_is_refused_before_any_run(tmp_path):
    # An earlier study's folder: its report and its points of other N were overwritten
    # in part and left in part, with exit 0.
    out = tmp_path / "s"
    (out / "points" / "replicated-n2-fps20").mkdir(parents=True)
    (out / "report.md").write_text("the earlier study")
    p = _hil("study", "hil_configs/study.yaml", "--vehicles", "1", "--duration", "1", "--out", str(out))
    assert p.returncode == 2 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert f"--out {out}: not empty" in p.stderr, p.stderr
    assert (out / "report.md").read_text() == "the earlier study"
    assert not (out / "points" / "replicated-n1-fps20").exists()


def test_largest_n_stops_at_the_first_point_that_fails():
    rows = [{"placement": "replicated", "fps": 20.0, "vehicles": n, "status": "ok", "holds": h}
            for n, h in ((1, True), (2, True), (4, False), (8, True))]
    assert largest_holding(rows) == {"replicated @ 20 fps": 2}
    rows[0]["holds"] = False
    assert largest_holding(rows) == {"replicated @ 20 fps": None}


@pytest.mark.slow
def test_netem_where_the_kernel_has_none_skips_the_distributed_points_with_the_reason(tmp_path):
    out = tmp_path / "study"
    p = _hil("study", "hil_configs/study.yaml", "--vehicles", "1", "--placement", "distributed", "--netem",
             "delay 5ms", "--out", str(out))
    doc = json.loads((out / "results.json").read_text())
    (pt,) = doc["points"]
    if pt["status"] == "ok":  # a kernel with sch_netem: the point ran through the impaired veth
        assert p.returncode == 0 and pt["e2e_p50_ms"] >= 10.0
        return
    assert p.returncode == 1 and pt["status"] == "skipped", (p.stdout, p.stderr)
    assert "netem" in pt["reason"] or "root" in pt["reason"] or "netns" in pt["reason"]
    assert "skipped" in (out / "report.md").read_text()


@pytest.mark.slow
def test_a_relative_out_and_config_mean_the_callers_folder(tmp_path, gl_backend):
    # The points ran with cwd=ROOT: `cd /tmp/x && hil study CONFIG --out st` wrote each
    # point's run into the checkout's st/, found no summary in /tmp/x/st and called every
    # point failed ("exit 0: report.html: ...") (README walkthrough).
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "s.yaml").write_text((ROOT / "hil_configs" / "study.yaml").read_text())
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "study", "cfg/s.yaml", "--vehicles", "1",
                        "--placement", "replicated", "--duration", "1", "--out", "st"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=200, env={**os.environ, "MUJOCO_GL": gl_backend})
    assert p.returncode in (0, 1), (p.stdout, p.stderr)
    (point,) = json.loads((tmp_path / "st" / "results.json").read_text())["points"]
    assert point["status"] == "ok", point
    assert (tmp_path / "st" / "points" / "replicated-n1-fps20" / "summary.json").is_file()
    assert not (ROOT / "st").exists()


def _tiny_study(out: Path) -> tuple[int, str, str]:
    p = _hil("study", "hil_configs/study.yaml", "--vehicles", "1", "2", "--duration", "2", "--out", str(out),
             timeout=400, env={**os.environ, "MUJOCO_GL": GL_BACKEND})
    return p.returncode, p.stdout, p.stderr


# Four 2-s points in real time (~14 s): beside the other tests (tests.conftest.beside);
# what it asserts of throughput is relative (2 vehicles carry more frames than 1).
beside(__name__, "tiny_study", _tiny_study, ahead_folder("tiny-study"))


@pytest.fixture(scope="module")
def tiny_study() -> tuple[int, str, str]:
    (result,) = ahead_results(__name__, "tiny_study")
    return result


@pytest.mark.slow
def test_a_tiny_study_in_both_placements(tiny_study):
    out = ahead_folder("tiny-study")
    code, stdout, stderr = tiny_study
    assert code in (0, 1), (stdout, stderr)
    doc = json.loads((out / "results.json").read_text())
    pts = {(r["placement"], r["vehicles"]): r for r in doc["points"]}
    assert set(pts) == {("replicated", 1), ("replicated", 2), ("distributed", 1), ("distributed", 2)}
    for (placement, n), r in pts.items():
        if placement == "distributed" and r["status"] == "skipped":
            assert r["reason"]  # no namespace here: skipped with the reason
            continue
        assert r["status"] == "ok", r
        assert 0 < r["total_fps"] <= 20 * n * 1.1 and r["fps_per_vehicle_min"] <= r["total_fps"]
        assert r["e2e_p50_ms"] > 0 and r["inference_p50_ms"] is not None and r["late_steps"] is not None
        summary = json.loads((Path(r["run_dir"]) / "summary.json").read_text()) if r.get("run_dir") else None
        assert summary is None or len(summary["vehicles"]) == n
        if summary is not None:  # the point's figures are its run's (the uplink was raw, unmapped, stamps)
            vs = summary["vehicles"].values()
            ups = sorted(v["splits_ms"]["uplink"]["p50_ms"] for v in vs)
            assert r["uplink_p50_ms"] == round((ups[(n - 1) // 2] + ups[n // 2]) / 2, 3), (r, ups)
            assert r["fps_per_vehicle_min"] == round(min(v["estimates_per_s"] for v in vs), 2)
    assert pts[("replicated", 2)]["total_fps"] > pts[("replicated", 1)]["total_fps"]
    with open(out / "results.csv") as f:
        assert len(list(csv.DictReader(f))) == 4
    report = (out / "report.md").read_text().splitlines()
    assert report[0].startswith("# Study") and report[1] == ""
    assert "largest N keeping" in report[2] and "frames/s" in report[2]  # the reading comes first
    fps_svg = (out / "fig_fps_per_vehicle.svg").read_text()
    assert fps_svg.startswith("<svg") and "10 fps floor" in fps_svg
    for name in ("fig_total_fps.svg", "fig_e2e_latency.svg", "fig_inference_latency.svg", "fig_lateness.svg",
                 "fig_late_steps.svg"):
        assert (out / name).read_text().startswith('<svg xmlns="http://www.w3.org/2000/svg"')
    assert (out / "report.html").is_file()


# --- the study's pictures (issue 25, item 7) ------------------------------------------

def _metrics(n: int) -> dict:
    return {"total_fps": 19.8 * n, "fps_per_vehicle_mean": 19.8 - 0.3 * n, "fps_per_vehicle_min": 19.7 - 0.4 * n,
            "e2e_p50_ms": 4.0 + n, "e2e_p99_ms": 9.0 + 2 * n, "e2e_std_ms": 1.1 * n, "inference_p50_ms": 2.0,
            "inference_p99_ms": 3.1, "inference_std_ms": 0.4, "uplink_p50_ms": 0.3, "late_steps": 3 * n,
            "steps_over_10ms": n, "lateness_p99_ms": 0.4 * n, "achieved_factor": 1.0, "kept_realtime": True,
            "floor_kept": True, "holds": True}


@pytest.fixture
def study_dir(tmp_path):
    """A study folder written from known points: N = 1, 2 (both hold), distributed skipped."""
    results = [PointResult(Point(Placement.REPLICATED, n, 20.0), "ok", None, None, 12.0, _metrics(n)) for n in (1, 2)]
    results += [PointResult(Point(Placement.DISTRIBUTED, n, 20.0), "skipped", "needs root") for n in (1, 2)]
    write_study(tmp_path, results, config="hil_configs/study.yaml", floor_fps=10.0, study_wall_s=60.0,
                loadavg="1.0 1.0 1.0")
    return tmp_path


def test_study_charts_are_svg_files_with_whole_vehicle_ticks_and_one_unit_each(study_dir):
    import xml.etree.ElementTree as ET

    svgs = sorted(study_dir.glob("fig_*.svg"))
    assert len(svgs) == 6
    for path in svgs:
        text = path.read_text()
        root = ET.fromstring(text)
        assert root.tag == "{http://www.w3.org/2000/svg}svg", path.name  # a file a browser shows as a picture
        ticks = [t.text for t in root.iter("{http://www.w3.org/2000/svg}text")
                 if t.get("text-anchor") == "middle" and t.text and t.text.replace(".", "").isdigit()]
        assert ticks == ["1", "2"], (path.name, ticks)  # the numbers of vehicles tried, nothing between
        ylabel = [t.text for t in root.iter("{http://www.w3.org/2000/svg}text") if t.get("transform")][0]
        assert not ("ms" in ylabel and "steps" in ylabel), ylabel
    steps = ET.fromstring((study_dir / "fig_late_steps.svg").read_text())
    yticks = [t.text for t in steps.iter("{http://www.w3.org/2000/svg}text") if t.get("text-anchor") == "end"]
    assert yticks and all(t.isdigit() for t in yticks), yticks  # counts: whole numbers


def test_study_says_when_every_n_tried_held(study_dir):
    report = (study_dir / "report.md").read_text()
    assert "held at every N tried (up to N = 2" in report and "is N = 2" not in report
    assert "replicated @ 20 fps: 2 (every N tried)" in report
    rows = [{"placement": "replicated", "fps": 20.0, "vehicles": n, "status": "ok", "holds": n < 4}
            for n in (1, 2, 4)]
    assert largest_holding(rows) == {"replicated @ 20 fps": 2}  # 4 was tried and failed: N = 2 is the answer


@pytest.mark.slow
@needs_chromium
def test_study_report_in_a_real_browser(study_dir, tmp_path):
    page = study_dir / "report.html"
    assert "<script" not in page.read_text() and "http" not in page.read_text()
    got = probe(page, tmp_path)
    assert_charts_legible(got, at_least=6)
    # each SVG file as report.md shows it: an image that loads, at its size
    gallery = study_dir / "gallery.html"
    gallery.write_text("<!DOCTYPE html><html><head><meta charset=utf-8></head><body>" + "".join(
        f'<img src="{p.name}">' for p in sorted(study_dir.glob("fig_*.svg"))) + "</body></html>")
    imgs = probe(gallery, tmp_path)["imgs"]
    assert len(imgs) == 6
    for img in imgs:
        assert img["complete"] and img["natural"][0] >= 700 and img["natural"][1] > 200, img
