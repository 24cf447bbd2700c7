"""Whole campaigns: a blind AI (says SAFE, never brakes) on the stopped-car scene
finds corner cases in every episode; they are kept, summarized and replayable, and a
sharded campaign merges into the same result as an unsharded one — the same cases
with the same ids: wall-clock timing anomalies (every frame here misses an
impossible deadline; latency spikes come and go with the machine's load) are
recorded but never made cases in lockstep episodes."""

from __future__ import annotations

import json
import os
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from hil.harness.search.campaign import Outcome, run_campaign
from hil.harness.search.episode import run_episode
from hil.harness.search.merge import merge
from hil.harness.search.sampling import draw_generation
from hil.harness.search.spec import load_spec
from tests.conftest import AHEAD_TIMEOUTS, GL_BACKEND, ahead, ahead_folder, ahead_results
from hil.common.errors import ConfigError

ROOT = Path(__file__).resolve().parents[3]
pytestmark = pytest.mark.slow

# Lockstep episodes, computed ahead (tests.conftest.ahead) with AHEAD_TIMEOUTS: a target
# starved there waits for its frame instead of dropping it (the same episodes, cases
# and ids whatever the load, which is what the tests below compare).
SPEC = {"name": "blind-search", "seed": 5, "episodes": 4,
        "run": {"mode": "lockstep", "duration_s": 2.0, "scenario": {"name": "stopped_car"},
                "target": {"command": ["{python}", "-m", "hil.targets.echo", "--throttle", "0.3"],
                           **AHEAD_TIMEOUTS},
                "corner_cases": {"history_s": 1.0, "after_s": 0.3,
                                 "on_anomalies": ["deadline_miss", "latency_spike", "jitter"]},
                "timing": {"thresholds": {"deadline_ms": {"end_to_end": 0.01}}}},
        "params": {"gap_m": [15, 30], "ego_speed_mps": [6, 12]}, "latency": {"ms": [0, 200]},
        "strategy": {"kind": "random"}}


def hil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, MUJOCO_GL=GL_BACKEND), check=False)


def write_spec(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / "blind.yaml"
    p.write_text(yaml.safe_dump(SPEC))
    return p


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory) -> Path:
    return write_spec(tmp_path_factory.mktemp("spec"))


def whole_campaign(folder: Path) -> Outcome:
    """The whole campaign on two workers."""
    return run_campaign(load_spec(write_spec(folder)), out=folder / "all", gl_backend=GL_BACKEND, workers=2,
                        install_signal_handlers=False)


def one_shard(folder: Path, i: int) -> tuple[int, str, str]:
    """Shard ``i`` of 2 run as a Kubernetes pod would: the CLI; (exit code, stdout,
    stderr). The two run at once where the work computed ahead leaves two workers free:
    the episodes are lockstep, so neither shard's result depends on the other's load."""
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "search", str(write_spec(folder / f"spec-{i}")),
                        "--shard", f"{i}/2", "--out", str(folder / f"shard-{i}"), "--workers", "1", "--no-progress"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300, check=False,
                       env=dict(os.environ, MUJOCO_GL=GL_BACKEND))
    return p.returncode, p.stdout, p.stderr


ahead(__name__, "campaign", whole_campaign, [(ahead_folder("search-campaign"),)])
ahead(__name__, "shards", one_shard, [(ahead_folder("search-shards"), i) for i in (0, 1)])


@pytest.fixture(scope="module")
def campaign() -> Outcome:
    (outcome,) = ahead_results(__name__, "campaign")
    return outcome


@pytest.fixture(scope="module")
def shards() -> Path:
    for code, stdout, stderr in ahead_results(__name__, "shards"):
        assert code == 0, (stdout, stderr)
        assert "2 episodes (shard " in stdout
    return ahead_folder("search-shards")


def episodes(folder: Path) -> dict[int, tuple]:
    con = sqlite3.connect(folder / "campaign.sqlite")
    try:
        return {r[0]: r[1:] for r in con.execute(
            "SELECT episode, seed, params, status, trace_hash, mismatches, score FROM episodes")}
    finally:
        con.close()


def test_campaign_finds_cases_and_summarizes_them(campaign):
    assert campaign.complete and len(campaign.ran) == 4
    s = json.loads((campaign.out_dir / "summary.json").read_text())
    assert s["episodes"] == {"planned": 4, "ran": 4, "by_status": {"ok": 4}, "missing": 0, "missing_first": [],
                             "complete": True}
    assert s["cases"]["total"] >= 8 and s["cases"]["by_cause"]["perception"] >= 8
    assert s["cases"]["episodes_with_cases"] == 4
    assert 0.04 < s["virtual_km"] < 0.1  # 4 x 2 s at 6-12 m/s, less braking into the car
    assert s["episodes_per_min"] > 0 and s["km_per_h"] > 0
    assert set(s["regions"]) == {"gap_m", "ego_speed_mps", "latency.ms"}
    assert len(s["slowest"]) == 4 and s["most_anomalous"][0]["score"] >= s["most_anomalous"][-1]["score"]
    html = (campaign.out_dir / "report.html").read_text()
    assert html.count("<svg") == 3 and "<circle" in html and "hil replay CAMPAIGN/episodes/e0000" in html
    assert "http" not in html  # self-contained
    con = sqlite3.connect(campaign.out_dir / "campaign.sqlite")
    rows = con.execute("SELECT episode, case_id, kind, mcap_path, episode_dir FROM cases").fetchall()
    assert len(rows) == s["cases"]["total"]
    for _ep, _cid, _kind, mcap_path, ep_dir in rows:
        assert (campaign.out_dir / mcap_path).is_file() and (campaign.out_dir / ep_dir / "config.json").is_file()


def test_an_episode_is_reproducible_from_its_seed_and_parameters(campaign, tmp_path):
    from hil.harness.search.db import CampaignDB

    with CampaignDB(campaign.out_dir / "campaign.sqlite", readonly=True) as db:
        camp = db.campaign()  # the campaign back from its stored spec
    d = draw_generation(camp, 0)[1]
    again = run_episode(camp, d, campaign_dir=tmp_path, shard="0/1", gl_backend=GL_BACKEND,
                        install_signal_handlers=False)
    first = episodes(campaign.out_dir)[1]
    assert again.status == "ok" and again.seed == first[0] and json.loads(first[1]) == again.params
    assert again.trace_hash == first[3], "same seed and parameters: the same ground-truth trace"
    assert json.loads(first[4]) == again.mismatches and first[5] == again.score


def test_a_case_found_replays(campaign):
    con = sqlite3.connect(campaign.out_dir / "campaign.sqlite")
    ep_dir, case_id = con.execute("SELECT episode_dir, case_id FROM cases WHERE kind = "
                                  "'mismatch.state_mismatch' AND severity = 'critical' ORDER BY episode").fetchone()
    p = hil("replay", str(campaign.out_dir / ep_dir), str(case_id))
    assert p.returncode == 0, (p.stdout, p.stderr)
    assert "reproduced" in p.stdout and "not reproduced" not in p.stdout
    p = hil("search", "cases", str(campaign.out_dir))
    assert p.returncode == 0 and "hil replay" in p.stdout and "episodes/e0000" in p.stdout


def test_shards_merge_into_the_unsharded_campaign(campaign, shards, tmp_path):
    a, b = episodes(shards / "shard-0"), episodes(shards / "shard-1")
    assert sorted(a) == [0, 2] and sorted(b) == [1, 3]
    r = merge(tmp_path / "merged", [shards / "shard-0", shards / "shard-1"])
    assert r.episodes == 4 and r.summary["episodes"]["complete"]
    merged = episodes(tmp_path / "merged")
    assert merged == {**a, **b}
    whole = episodes(campaign.out_dir)
    assert {i: v[:4] for i, v in merged.items()} == {i: v[:4] for i, v in whole.items()}, "same seeds, values, traces"
    assert r.summary["campaign"]["id"] == campaign.summary["campaign"]["id"]
    assert {s["shard"] for s in r.summary["shards"]} == {"0/2", "1/2"}
    for i in range(4):
        assert (tmp_path / "merged" / "episodes" / f"e{i:05d}" / "run.mcap").is_file()
    # A merged campaign's case replays from its new place too.
    con = sqlite3.connect(tmp_path / "merged" / "campaign.sqlite")
    (ep_dir, case_id), = con.execute("SELECT episode_dir, case_id FROM cases WHERE kind = "
                                     "'mismatch.missed_object' AND episode = 1").fetchall()
    p = hil("replay", str(tmp_path / "merged" / ep_dir), str(case_id))
    assert p.returncode == 0 and "reproduced" in p.stdout and "not reproduced" not in p.stdout, p.stdout
    assert not (shards / "shard-1" / ep_dir / "replays").exists(), "the shard's folder is left as it was"


def case_set(folder: Path) -> list[tuple]:
    con = sqlite3.connect(folder / "campaign.sqlite")
    try:
        return con.execute("SELECT episode, case_id, vehicle, sim_time_ns, kind, cause, severity FROM cases "
                           "ORDER BY episode, case_id").fetchall()
    finally:
        con.close()


def test_lockstep_episodes_record_timing_anomalies_but_make_no_case_of_them(campaign):
    con = sqlite3.connect(campaign.out_dir / "campaign.sqlite")
    anomalies = [n for (n,) in con.execute("SELECT anomalies FROM episodes")]
    assert len(anomalies) == 4 and all(n > 0 for n in anomalies), "every frame misses its deadline"
    kinds = {k for (k,) in con.execute("SELECT kind FROM cases")}
    assert kinds and all(k.startswith("mismatch.") for k in kinds), kinds
    s = json.loads((campaign.out_dir / "summary.json").read_text())
    assert s["cases"]["by_cause"]["timing"] == 0


def test_sharded_and_unsharded_campaigns_find_the_same_cases(campaign, shards, tmp_path):
    # The unsharded campaign ran 2 episodes at a time in one folder, the shards one at a
    # time each: different load, the same cases with the same ids.
    merge(tmp_path / "merged", [shards / "shard-0", shards / "shard-1"])
    merged, whole = case_set(tmp_path / "merged"), case_set(campaign.out_dir)
    assert merged and merged == whole
    assert merged == sorted(case_set(shards / "shard-0") + case_set(shards / "shard-1"))


def test_merge_refuses_other_campaigns_duplicates_and_existing_output(shards, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(shards / "shard-1", other)
    con = sqlite3.connect(other / "campaign.sqlite")
    con.execute("UPDATE campaign SET id = 'feedfacefeedface', name = 'else'")
    con.commit()
    con.close()
    with pytest.raises(ConfigError, match="campaign feedfacefeedface \\(else\\) differs"):
        merge(tmp_path / "m1", [shards / "shard-0", other])
    with pytest.raises(ConfigError, match="episode 0 is in both"):
        merge(tmp_path / "m2", [shards / "shard-0", _copy(shards / "shard-0", tmp_path / "dup")])
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    p = hil("search", "merge", str(existing), str(shards / "shard-0"), str(shards / "shard-1"))
    assert p.returncode == 2 and "exists already" in p.stderr and "Traceback" not in p.stderr
    assert (existing / "keep.txt").read_text() == "mine" and sorted(os.listdir(existing)) == ["keep.txt"]
    assert not (tmp_path / "m1").exists() and not (tmp_path / "m2").exists()
    assert not list(tmp_path.glob("*.partial"))


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_an_existing_campaign_is_resumed_not_overwritten(campaign, spec_file):
    c = load_spec(spec_file)
    with pytest.raises(ConfigError, match="holds a campaign already"):
        run_campaign(c, out=campaign.out_dir, gl_backend=GL_BACKEND, install_signal_handlers=False)
    again = run_campaign(c, out=campaign.out_dir, gl_backend=GL_BACKEND, resume=True, install_signal_handlers=False)
    assert again.ran == [] and again.already_done == 4 and again.complete
    with pytest.raises(ConfigError, match="holds campaign .* not "):
        run_campaign(load_spec(spec_file, seed=6), out=campaign.out_dir, gl_backend=GL_BACKEND, resume=True,
                     install_signal_handlers=False)


def test_a_guided_campaign_draws_each_generation_from_the_last(spec_file, tmp_path):
    from hil.harness.search.db import CampaignDB
    from hil.harness.search.sampling import Past

    c = load_spec(spec_file, strategy="mutate")
    c = type(c).from_json({**c.as_json(), "strategy": {**c.as_json()["strategy"], "generation": 2, "explore": 0.0}})
    oc = run_campaign(c, out=tmp_path / "guided", gl_backend=GL_BACKEND, workers=2, install_signal_handlers=False)
    assert oc.complete, [(r.index, r.status, r.ended_by, r.error) for r in oc.ran]
    with CampaignDB(tmp_path / "guided" / "campaign.sqlite", readonly=True) as db:
        eps = db.episodes()
    assert [e["generation"] for e in eps] == [0, 0, 1, 1]
    assert all(e["origin"].startswith("mutate e0000") for e in eps[2:]), [e["origin"] for e in eps]
    history = [Past(e["episode"], tuple(e["unit"]), e["score"]) for e in eps[:2]]
    assert [d.values for d in draw_generation(c, 1, history)] == [e["params"] for e in eps[2:]]


def test_sigterm_stops_the_campaign_and_resume_finishes_it(spec_file, tmp_path):
    out = tmp_path / "stopped"
    cmd = [sys.executable, "-m", "hil.harness.cli.main", "search", str(spec_file), "--out", str(out), "--workers", "1",
           "--no-progress", "--episodes", "6"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, MUJOCO_GL=GL_BACKEND))
    try:
        for line in proc.stdout:  # wait for the first finished episode, then stop the campaign
            if line.startswith("e0000"):
                proc.terminate()
                break
        rest, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, (rest, err)
    assert "stopped" in rest and "--resume" in rest and "Traceback" not in err
    done = episodes(out)
    assert 1 <= len(done) < 6 and all(v[2] == "ok" for v in done.values())
    s = json.loads((out / "summary.json").read_text())
    assert not s["episodes"]["complete"] and s["episodes"]["missing"] == 6 - len(done)
    p = hil("search", str(spec_file), "--out", str(out), "--workers", "2", "--no-progress", "--episodes", "6",
            "--resume")
    assert p.returncode == 0, (p.stdout, p.stderr)
    assert f"6 episodes, {len(done)} done already" in p.stdout
    assert sorted(episodes(out)) == list(range(6))
    s = json.loads((out / "summary.json").read_text())
    assert s["episodes"]["complete"]
    # The last line's running totals count the episodes before the resume too (its
    # episode count did, its km and cases did not).
    last = [ln for ln in p.stdout.splitlines() if ln.startswith("e0000")][-1]
    m = re.search(r"\[6/6, ([0-9.]+) km, (\d+) cases,", last)
    assert m and abs(float(m[1]) - s["virtual_km"]) < 0.0011 and int(m[2]) == s["cases"]["total"], (last, s)
