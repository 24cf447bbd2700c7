"""``hil report``: one self-contained HTML page from a real run, from a killed run's
truncated MCAP, and one-line errors (exit 2) for what is not a run."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from hil.harness.cli.main import main as hil_main
from hil.harness.config.loading import parse_config
from hil.harness.record.recorder import Recorder
from hil.harness.record.run_folder import RecordedEvent, read_run
from hil.harness.report import plots as rp
from hil.harness.report.run_report import build_report, write_report
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND
from tests.harness.browser import assert_charts_legible, chromium, needs_chromium, probe

ROOT = Path(__file__).resolve().parents[3]
SECTIONS = ("Run", "Fleet overview", "Latency per stage", "End-to-end latency over time",
            "Frames per second over time", "Target clock: offset and uncertainty", "Events", "Corner cases")
CASES_SQL = ("CREATE TABLE cases (id INTEGER PRIMARY KEY, run TEXT, scenario TEXT, seed INTEGER, params TEXT, "
             "config_hash TEXT, vehicle TEXT, sim_time_ns INTEGER, kind TEXT, summary TEXT, mcap_path TEXT)")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 60 ms of inference per frame at 20 fps with a 100 ms timeout: the target falls
    # behind and skips frames, so the run has drops, late estimates and their events.
    out = prepare_out_dir(tmp_path_factory.mktemp("report") / "run")
    cfg = parse_config({
        "name": "rpt", "duration_s": 2.0, "progress": False,
        "scenario": {"name": "stopped_car", "params": {"gap_m": 40.0, "ego_speed_mps": 6.0}},
        "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--infer-ms", "60"],
                   "estimate_timeout_s": 0.1},
        # The cases below are written by hand with known content; the run's own
        # detector is tested in test_corner_cases.py.
        "corner_cases": {"enabled": False}})
    execute(cfg, out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    with sqlite3.connect(out / "corner_cases.sqlite") as con:  # as the corner-case detector writes it
        con.execute(CASES_SQL)
        con.executemany("INSERT INTO cases VALUES (?,?,?,?,?,?,?,?,?,?,?)", [
            (1, "rpt", "stopped_car", 0, '{"gap_m": 40.0}', "abc", "ego0", 1_000_000_000, "latency_spike",
             "end-to-end 61 ms against a 5 ms baseline", "corner_cases/case-1.mcap"),
            (2, "rpt", "stopped_car", 0, '{"gap_m": 40.0}', "abc", "ego0", 500_000_000, "state_mismatch",
             "SAFE where ground truth says STOP", "corner_cases/case-2.mcap")])
    con.close()
    return out


def _svgs(html: str) -> list[ET.Element]:
    return [ET.fromstring(s) for s in re.findall(r"<svg\b.*?</svg>", html, re.DOTALL)]


def test_report_is_self_contained_and_has_every_section(run_dir: Path) -> None:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "report", str(run_dir)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=60, check=False)
    assert p.returncode == 0, p.stderr
    assert "report.html" in p.stdout
    html = (run_dir / "report.html").read_text()

    # Nothing loaded from anywhere: no remote src/href, no stylesheet or script links.
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:|//)""", html, re.IGNORECASE)
    assert "<link" not in html and "<script" not in html and "http" not in html
    for s in SECTIONS:
        assert re.search(rf"<h2[^>]*>{re.escape(s)}</h2>", html), s
    # navigation: every section has an anchor the bar links to
    for anchor in re.findall(r'<nav class="top">(.*?)</nav>', html)[0].split('href="#')[1:]:
        assert f'id="{anchor.split(chr(34))[0]}"' in html, anchor
    # the estimate timeout (100 ms) and the default end-to-end deadline (100 ms) are drawn
    assert "estimate timeout 100 ms" in html and "deadline 100 ms" in html
    # events readable: value against threshold with units, sim time; cases counted in words
    assert "value vs threshold" in html and "2 cases in" in html
    assert "harness_time_ns" not in html

    # Every chart is well-formed SVG: box plot, 8 histograms, timeline, frame rate, clock.
    svgs = _svgs(html)
    assert len(svgs) >= 12
    assert all(s.tag == "svg" for s in svgs)

    # Exact percentiles: the table agrees with summary.json (same records, same method).
    summary = json.loads((run_dir / "summary.json").read_text())
    v = summary["vehicles"]["ego0"]
    e2e = v["latency_ms"]["end_to_end"]
    row = re.search(r"<tr><td>end_to_end</td>(.*?)</tr>", html).group(1)
    for key in ("p50_ms", "p90_ms", "p99_ms", "max_ms"):
        assert f">{e2e[key]:.3f}<" in row, (key, row)

    # The fixture's drops show as events under the timeline and in the events table.
    assert v["dropped"] > 0
    assert "dropped_frame" in html

    # One thumbnail per corner case, real JPEG of the camera's size.
    images = re.findall(r'src="data:image/(\w+);base64,([^"]+)"', html)
    assert len(images) == 2
    # drawn at the image's aspect ratio (320x240 shown 320x240), never stretched
    assert len(re.findall(r'<img [^>]*width="320" height="240"', html)) == 2
    for fmt, b64 in images:
        assert fmt == "jpeg"
        img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
        assert img.shape == (240, 320, 3)
    assert "SAFE where ground truth says STOP" in html


def test_write_report_api_and_generic_event_kinds(run_dir: Path, tmp_path: Path) -> None:
    assert write_report(run_dir) == run_dir / "report.html"
    d = read_run(run_dir)
    t = d.t_start_ns + 1_000_000_000
    d.events.append(RecordedEvent(t, "deadline_miss", ("ego0",), "error", {"kind": "deadline_miss", "value_ms": 61}))
    d.events.append(RecordedEvent(t, "clock_step", (), None, {"kind": "clock_step"}))
    html = build_report(d)
    assert "deadline_miss" in html and "clock_step" in html
    assert "#d62728" in html  # severity "error" colours its tick


def test_no_corner_case_db_says_so(run_dir: Path, tmp_path: Path) -> None:
    folder = tmp_path / "nocases"
    folder.mkdir()
    for name in ("run.mcap", "summary.json"):
        shutil.copy(run_dir / name, folder / name)
    html = write_report(folder).read_text()
    assert "no corner cases recorded" in html


def test_clock_topic_is_used_when_present(tmp_path: Path) -> None:
    # A synthetic run: the future /V/clock estimator topic with skew and uncertainty.
    folder = tmp_path / "synthetic"
    folder.mkdir()
    with Recorder(folder / "run.mcap") as rec:
        rec.register_json_channel("/ego0/pipeline", "hil.PipelineRecord", {"type": "object"})
        rec.register_json_channel("/ego0/clock", "hil.ClockEstimate", {"type": "object"})
        rec.register_json_channel("/events", "hil.Event", {"type": "object"})
        for k in range(40):
            t0 = 10**12 + k * 50_000_000
            rec.write_json("/ego0/pipeline", {"vehicle": "ego0", "frame_id": k, "status": "ok", "sim_time_ns": k,
                                              "t0_ns": t0, "t_tx_ns": t0 + 10, "t0p_ns": t0 + 4_000_000,
                                              "stages_ns": {"end_to_end": 4_000_000 + k * 1000}},
                           log_time_ns=t0 + 4_000_000, publish_time_ns=t0)
            rec.write_json("/ego0/clock", {"offset_ns": 5e6 + k * 600, "skew_ppm": 12.5, "uncertainty_ns": 40_000},
                           log_time_ns=t0, publish_time_ns=t0)
        rec.write_json("/events", {"kind": "latency_spike", "vehicle": "ego0", "severity": "warning"},
                       log_time_ns=10**12, publish_time_ns=10**12)
    d = read_run(folder)
    assert d.clock_source["ego0"] == "/ego0/clock" and not d.truncated
    html = build_report(d)
    assert "+12.50" in html and "latency_spike" in html and "#f58518" in html
    assert "no summary.json" in html  # said, not failed
    for s in _svgs(html):
        assert s.tag == "svg"


def test_truncated_mcap_is_reported_from_its_complete_chunks(run_dir: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    killed = tmp_path / "killed"
    killed.mkdir()
    data = (run_dir / "run.mcap").read_bytes()
    (killed / "run.mcap").write_bytes(data[: int(len(data) * 0.7)])  # no summary.json: killed runs have none
    assert hil_main(["report", str(killed)]) == 0
    out = capsys.readouterr().out
    assert "truncated" in out
    html = (killed / "report.html").read_text()
    assert "run.mcap is truncated" in html
    assert "<td>end_to_end</td>" in html  # latency from the salvaged records


def _one_line_error(argv: list[str], capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    assert hil_main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], lines[0]


def test_bad_inputs_give_one_line_and_exit_2(run_dir: Path, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_error(["report", str(tmp_path / "nowhere")], capsys, "nowhere", "no such file")
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(["report", str(empty)], capsys, "empty", "not a run folder")

    text = tmp_path / "text"
    text.mkdir()
    (text / "summary.json").write_text("these are my notes, not JSON\n")
    _one_line_error(["report", str(text)], capsys, str(text / "summary.json"), "not a run summary")

    cut = tmp_path / "cut"
    cut.mkdir()
    full = (run_dir / "summary.json").read_text()
    (cut / "summary.json").write_text(full[: len(full) // 2])
    shutil.copy(run_dir / "run.mcap", cut / "run.mcap")
    _one_line_error(["report", str(cut)], capsys, "summary.json", "truncated JSON")

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "run.mcap").write_text("not a recording\n")
    _one_line_error(["report", str(foreign)], capsys, "run.mcap", "not an MCAP file")

    stub = tmp_path / "stub"
    stub.mkdir()
    (stub / "run.mcap").write_bytes((run_dir / "run.mcap").read_bytes()[:12])
    _one_line_error(["report", str(stub)], capsys, "run.mcap", "truncated")


# --- pictures that tell the truth (issue 25, item 7) ----------------------------------

STATE_EVIDENCE = {"frame_id": 48, "sim_time_t0_ns": 4_800_000_000, "sim_time_apply_ns": 4_814_000_000,
                  "latency_sim_ns": 14_000_000, "latency_ns": 4_368_142, "belief": {"state": "STOP"},
                  "truth_t0": {"state": "SLOW"}, "truth_apply": {"state": "SLOW"}}


def _state_mismatch(t_ns: int) -> dict:
    from hil.harness.vocab.events import Event, EventKind, Severity

    return Event(EventKind("mismatch.state_mismatch"), t_ns, "ego0", (46, 47, 48), 4_800_000_000, 2.0, 1.0, "state",
                 Severity.INFO, "perception", (), "AI said STOP where truth says SLOW",
                 {"entity": None, "evidence": STATE_EVIDENCE}).to_json()


@pytest.fixture(scope="module")
def paced_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A synthetic run with known truth: 10 fps for 6 s, capture jittered by up to
    ±20 ms (a render's spread), end-to-end 4-6 ms, a 100 ms deadline and a 500 ms
    timeout in its config, a target clock 10 ppm fast seen only through raw clock-sync
    samples (round trip 200 µs), a state mismatch and its corner case."""
    from hil.harness.cases.casebook import SCHEMA

    folder = tmp_path_factory.mktemp("paced") / "run"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({
        "name": "paced", "seed": 3, "scenario": {"name": "stopped_car", "params": {"gap_m": 40.0}},
        "camera": {"fps": 10.0}, "target": {"estimate_timeout_s": 0.5}, "timing": {}}))
    rng = np.random.default_rng(0)
    t_start = 10**12
    with Recorder(folder / "run.mcap") as rec:
        rec.register_json_channel("/ego0/pipeline", "hil.PipelineRecord", {"type": "object"})
        rec.register_json_channel("/ego0/clock_sync", "hil.ClockSync", {"type": "object"})
        rec.register_json_channel("/events", "hil.Event", {"type": "object"})
        for k in range(60):
            t0 = t_start + k * 100_000_000 + int(rng.uniform(-20e6, 20e6))
            e2e = int(rng.uniform(4e6, 6e6))
            rec.write_json("/ego0/pipeline", {"vehicle": "ego0", "frame_id": k, "status": "ok",
                                              "sim_time_ns": k * 100_000_000, "t0_ns": t0, "t0p_ns": t0 + e2e,
                                              "t_apply_ns": t0 + e2e + 300_000, "stages_ns": {"end_to_end": e2e}},
                           log_time_ns=t0 + e2e, publish_time_ns=t0)
        for k in range(25):  # offset grows 10 ppm: 1 µs per 100 ms
            t = t_start + k * 250_000_000
            rec.write_json("/ego0/clock_sync", {"offset_ns": 5_000_000 + (t - t_start) * 10 // 10**6,
                                                "delay_ns": 200_000}, log_time_ns=t, publish_time_ns=t)
        ev = _state_mismatch(t_start + 4_803_000_000)
        rec.write_json("/events", ev, log_time_ns=ev["harness_time_ns"], publish_time_ns=ev["harness_time_ns"])
    (folder / "corner_cases").mkdir()
    (folder / "corner_cases" / "case-0001.mcap").write_bytes((folder / "run.mcap").read_bytes())
    with sqlite3.connect(folder / "corner_cases.sqlite") as con:
        con.executescript(SCHEMA)
        con.execute("INSERT INTO cases (id, run, scenario, seed, params, config_hash, vehicle, sim_time_ns, "
                    "harness_time_ns, kind, cause, severity, summary, event, mcap_path, messages) VALUES "
                    "(1, 'paced', 'stopped_car', 3, '{}', 'abc', 'ego0', 4800000000, ?, 'mismatch.state_mismatch', "
                    "'perception', 'info', 'AI said STOP where truth says SLOW', ?, 'corner_cases/case-0001.mcap', 9)",
                    (ev["harness_time_ns"], json.dumps(ev)))
    con.close()
    return folder


def _chart(html: str, label: str) -> ET.Element:
    (svg,) = [s for s in _svgs(html) if s.get("aria-label") == label]
    return svg


def _plot_box(svg: ET.Element) -> tuple[float, float, float, float]:
    rect = next(r for r in svg.iter("rect") if r.get("fill") == "#fafafa")
    x, y = float(rect.get("x")), float(rect.get("y"))
    return x, y, x + float(rect.get("width")), y + float(rect.get("height"))


def _texts_inside(svg: ET.Element) -> list[str]:
    """The texts whose anchor point lies in the plot area (where the data is)."""
    x0, y0, x1, y1 = _plot_box(svg)
    return [t.text or "" for t in svg.iter("text") if t.get("x") is not None
            and x0 < float(t.get("x")) < x1 and y0 < float(t.get("y")) < y1]


def _path_ys(svg: ET.Element, title: str) -> list[float]:
    path = next(p for p in svg.iter("path") if (p.findtext("title") or "") == title)
    return [float(v) for v in re.findall(r"[ML][\d.]+ ([\d.]+)", path.get("d"))]


def test_frame_rate_is_counted_in_whole_frame_periods(paced_run: Path) -> None:
    # 10 fps captured with ±20 ms of jitter: 0.25 s bins held 2 or 3 frames (8/s, 12/s
    # across the 10/s floor); bins of whole periods hold the same number every time.
    html = build_report(read_run(paced_run))
    svg = _chart(html, "ego0 (bins of 3 frame periods, 0.3 s)")
    sent, applied = _path_ys(svg, "frames sent/s"), _path_ys(svg, "estimates applied/s")
    assert len(sent) == 20 and len(set(sent)) == 1, sent
    assert len(applied) == 20 and set(applied) == set(sent), applied
    x0, y0, x1, y1 = _plot_box(svg)
    floor = [float(ln.get("y1")) for ln in svg.iter("line") if (ln.findtext("title") or "").startswith("frame-rate")]
    assert floor == [pytest.approx(sent[0], abs=0.1)]  # the rate sits on the 10/s floor, as it truly does
    assert _texts_inside(svg) == []
    from hil.harness.report.timeseries import rate_bins

    rates = rate_bins(np.array([k / 10 + 0.02 * (-1) ** k for k in range(60)]), start_s=-0.05,
                                 period_s=0.1, frames=3, end_s=5.9)[1]
    assert set(rates.round(9)) == {10.0}


def test_fleet_chart_is_scaled_to_the_data_and_names_the_budget_beyond_it(paced_run: Path) -> None:
    # 4-6 ms of data under a 100 ms deadline: the axis fits the data, the deadline and
    # the timeout are named above the chart, and no text is drawn over the points.
    html = build_report(read_run(paced_run))
    for label in ("all vehicles", "ego0"):
        svg = _chart(html, label)
        ticks = [float(t.text) for t in svg.iter("text") if t.get("text-anchor") == "end" and t.text
                 and re.fullmatch(r"[\d.]+", t.text)]
        assert max(ticks) <= 10, ticks  # not 0-100 ms
        assert _texts_inside(svg) == [], label
        legend = [t.text for t in svg.iter("text")]
        assert "deadline 100 ms: above the chart" in legend
        assert "estimate timeout 500 ms (dropped beyond): above the chart" in legend
    # a deadline near the data is drawn on the chart, named in the legend
    near = rp.line_chart(series=[rp.Series("e2e", [0, 1, 2], [60.0, 80.0, 90.0], "#000", "points")],
                         rules=[rp.Rule("deadline 100 ms", 100.0)], x_label="t", y_label="ms")
    svg = ET.fromstring(near)
    assert "deadline 100 ms" in [t.text for t in svg.iter("text")]
    assert any((ln.findtext("title") or "") == "deadline 100 ms" for ln in svg.iter("line"))
    assert _texts_inside(svg) == []


def test_clock_skew_is_shown_with_its_bound(paced_run: Path) -> None:
    # Raw samples of a clock 10 ppm fast: the fitted skew carries its bound, and the
    # truth lies within it.
    html = build_report(read_run(paced_run))
    cell = re.search(r"<td class=n>([+-][\d.]+) ± ([\d.]+)</td></tr></table><h2 id=\"events\">", html)
    assert cell, re.findall(r"skew.{0,400}", html)[:1]
    skew, bound = float(cell.group(1)), float(cell.group(2))
    assert abs(skew - 10.0) <= bound and bound < 50


def test_events_and_case_evidence_read_as_words(paced_run: Path) -> None:
    html = build_report(read_run(paced_run))
    assert "AI STOP, truth SLOW" in html
    assert "2 state" not in html and "None" not in html
    # the case's evidence whole: no key cut in the middle, times in s, durations in ms
    for part in ("sim time apply 4.814 s", "latency 4.368 ms", "truth apply (state SLOW))"):
        assert part in html, part
    d = read_run(paced_run)
    assert f"{(d.events[0].t_ns - d.t_start_ns) / 1e9:.3f} s since the first frame" in html
    assert "harness_time" not in html


def test_the_clock_table_shows_the_summarys_final_offset_beside_the_samples_median(run_dir: Path) -> None:
    # The table had the samples' median offset only, which a reader could not find in
    # summary.json (a skewed clock's offset moves: 0.019 ms there against 2.107 here).
    html = build_report(read_run(run_dir))
    c = json.loads((run_dir / "summary.json").read_text())["vehicles"]["ego0"]["clock"]
    assert "final offset (ms, summary.json)" in html
    assert f"{c['offset_ns'] / 1e6:+.3f} ± {c['uncertainty_ns'] / 1e6:.3f}" in html


def test_a_killed_run_says_what_ran_from_its_config(run_dir: Path, tmp_path: Path) -> None:
    killed = tmp_path / "killed"
    killed.mkdir()
    data = (run_dir / "run.mcap").read_bytes()
    (killed / "run.mcap").write_bytes(data[: int(len(data) * 0.7)])
    shutil.copy(run_dir / "config.json", killed / "config.json")
    html = write_report(killed).read_text()
    summary = json.loads((run_dir / "summary.json").read_text())
    row = lambda name: re.search(rf"<tr><th>{name}</th><td>(.*?)</td></tr>", html).group(1)  # noqa: E731
    assert (row("name"), row("scenario"), row("seed")) == ("rpt", "stopped_car", "0")
    assert summary["config_hash"] in row("config hash")
    assert "config.json" in row("read from")


def test_report_written_elsewhere_keeps_its_links(run_dir: Path, tmp_path: Path) -> None:
    (run_dir / "corner_cases").mkdir(exist_ok=True)
    (run_dir / "corner_cases" / "case-1.mcap").write_bytes((run_dir / "run.mcap").read_bytes()[:64])
    out = tmp_path / "elsewhere" / "deep" / "page.html"
    out.parent.mkdir(parents=True)
    assert hil_main(["report", str(run_dir), "--out", str(out)]) == 0
    hrefs = [h for h in re.findall(r'href="([^"#][^"]*)"', out.read_text())]
    assert hrefs, "the case recording is linked"
    for h in hrefs:
        assert (out.parent / h).resolve() == (run_dir / "corner_cases" / "case-1.mcap").resolve(), h


def test_recorder_count_agrees_with_the_file_and_the_report(run_dir: Path, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    summary = json.loads((run_dir / "summary.json").read_text())
    with open(run_dir / "run.mcap", "rb") as f:
        in_file = make_reader(f).get_summary().statistics.message_count
    rec = summary["recorder"]
    assert rec["written"] == in_file and 0 < rec["derived"] < in_file
    html = write_report(run_dir).read_text()
    assert f"{in_file} messages written ({rec['derived']} of them Foxglove views" in html
    assert f"{in_file} messages" in re.search(r"<tr><th>run.mcap</th><td>(.*?)</td>", html).group(1)
    # a summary of an older harness, which left the derived views out, is not shown as if it agreed
    old = tmp_path / "old"
    old.mkdir()
    shutil.copy(run_dir / "run.mcap", old / "run.mcap")
    summary["recorder"] = {"written": in_file - rec["derived"], "dropped": 0}
    (old / "summary.json").write_text(json.dumps(summary))
    html = write_report(old).read_text()
    assert (f"{in_file - rec['derived']} messages counted, 0 dropped; run.mcap holds {in_file}: the harness that "
            "wrote it did not count the Foxglove views") in html


def test_the_run_process_cost_by_thread_is_the_summarys(run_dir: Path) -> None:
    threads = json.loads((run_dir / "summary.json").read_text())["harness_cost"]["threads_us_per_frame"]
    row = re.search(r"<tr><th>harness CPU by thread</th><td>(.*?)</td>", write_report(run_dir).read_text()).group(1)
    shown = re.findall(r"([\w:-]+) ([\d.]+) µs", row)
    assert {role: float(us) for role, us in shown} == threads and len(shown) == len(threads) >= 5
    assert [float(us) for _, us in shown] == sorted(threads.values(), reverse=True)  # the costliest first


# --- as a person sees it: headless Chromium -------------------------------------------


@pytest.mark.slow
@needs_chromium
def test_report_in_a_real_browser(run_dir: Path, tmp_path: Path) -> None:
    page = write_report(run_dir)
    got = probe(page, tmp_path)
    # every chart has a size, no label covers data or another label, the page fits the window
    assert_charts_legible(got, at_least=12)
    # every thumbnail decoded and drawn at its own aspect ratio
    assert len(got["imgs"]) == 2
    for img in got["imgs"]:
        (w, h), (nw, nh) = img["box"], img["natural"]
        assert img["complete"] and nw > 0 and nh > 0 and w > 100
        assert abs(w / h - nw / nh) < 0.02, (w, h, nw, nh)

    # A screenshot of the page as rendered: not blank (kept next to the run for a look).
    shot = tmp_path / "report.png"
    chromium(["--window-size=1200,2400", f"--screenshot={shot}"], page.as_uri())
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (2400, 1200)
    assert img.std() > 20  # text, tables and charts, not an empty page
