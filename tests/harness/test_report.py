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
from hil.harness.config.model import parse_config
from hil.harness.record.recorder import Recorder
from hil.harness.record.run_folder import RecordedEvent, read_run
from hil.harness.report.run_report import build_report, write_report
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[2]
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


# --- as a person sees it: headless Chromium -------------------------------------------

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-extensions", "--no-first-run", "--hide-scrollbars", "--mute-audio",
                 "--enable-logging=stderr", "--v=0"]
# Injected into a copy of the page (the report itself holds no script): records
# script errors, then measures every chart and picture once the page has loaded.
_PROBE = """<script>
window.__errors = [];
window.addEventListener('error', e => window.__errors.push(String(e.message || e.type)), true);
window.addEventListener('load', () => {
  const box = el => { const r = el.getBoundingClientRect(); return [r.width, r.height]; };
  const out = {errors: window.__errors,
    svgs: [...document.querySelectorAll('svg')].map(box),
    imgs: [...document.querySelectorAll('img')].map(i => ({box: box(i), natural: [i.naturalWidth, i.naturalHeight],
                                                           complete: i.complete})),
    width: document.documentElement.scrollWidth, viewport: window.innerWidth};
  document.body.setAttribute('data-probe', btoa(JSON.stringify(out)));
});
</script>"""


def _chromium(args: list[str], url: str) -> subprocess.CompletedProcess[str]:
    assert CHROMIUM is not None
    return subprocess.run([CHROMIUM, *CHROMIUM_ARGS, *args, url], capture_output=True, text=True, timeout=90,
                          check=False, env={**os.environ, "HOME": os.environ.get("TMPDIR", "/tmp")})


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="no chromium: `make test` installs it where apt-get works")
def test_report_in_a_real_browser(run_dir: Path, tmp_path: Path) -> None:
    page = write_report(run_dir).read_text()
    probed = tmp_path / "probed.html"
    probed.write_text(page.replace("<head>", "<head>" + _PROBE, 1))
    p = _chromium(["--window-size=1200,900", "--virtual-time-budget=10000", "--dump-dom"], probed.as_uri())
    m = re.search(r'data-probe="([^"]+)"', p.stdout)
    assert m, p.stderr[-2000:]
    got = json.loads(base64.b64decode(m.group(1)))
    assert got["errors"] == []
    console = [ln for ln in p.stderr.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
    assert console == [], console
    # every chart has a size; the page fits the window (charts shrink, nothing overflows)
    assert len(got["svgs"]) >= 12
    assert all(w > 50 and h > 30 for w, h in got["svgs"]), got["svgs"]
    assert got["width"] <= got["viewport"], (got["width"], got["viewport"])
    # every thumbnail decoded and drawn at its own aspect ratio
    assert len(got["imgs"]) == 2
    for img in got["imgs"]:
        (w, h), (nw, nh) = img["box"], img["natural"]
        assert img["complete"] and nw > 0 and nh > 0 and w > 100
        assert abs(w / h - nw / nh) < 0.02, (w, h, nw, nh)

    # A screenshot of the page as rendered: not blank (kept next to the run for a look).
    shot = tmp_path / "report.png"
    _chromium(["--window-size=1200,2400", f"--screenshot={shot}"], (run_dir / "report.html").as_uri())
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (2400, 1200)
    assert img.std() > 20  # text, tables and charts, not an empty page
