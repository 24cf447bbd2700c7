"""The campaign layer without running episodes: specs, seeds, draws, shards, scores."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.common.errors import ConfigError
from hil.harness.search.sampling import Past, draw_generation, episode_seed, score
from hil.harness.search.shard import Shard, parse_shard
from hil.harness.search.spec import load_spec, resolve_spec
from hil.scenarios.registry import get as scenario_def

ROOT = Path(__file__).resolve().parents[3]

BASE = {"name": "t", "seed": 1, "episodes": 24,
        "run": {"mode": "lockstep", "duration_s": 2.0, "scenario": {"name": "stopped_car"}},
        "params": {"gap_m": [15, 60], "ego_speed_mps": None}, "latency": {"ms": [0, 300], "std_ms": [0, 50]}}


def spec(**over):
    data = {**BASE, **over}
    return resolve_spec(data, source="t.yaml")


def test_random_draws_are_reproducible_from_the_seed_and_in_range():
    c = spec()
    a, b = draw_generation(c, 0), draw_generation(c, 0)
    assert a == b and len(a) == c.strategy.generation
    assert draw_generation(spec(seed=2), 0)[0].values != a[0].values
    for d in a:
        assert 15 <= d.values["gap_m"] <= 60 and 0 <= d.values["ego_speed_mps"] <= 30
        assert 0 <= d.values["latency.ms"] <= 300 and d.seed == episode_seed(1, d.index)
    # An episode's draw is its own: it does not depend on the generation size.
    other = spec(strategy={"generation": 4})
    assert draw_generation(other, 1)[0].values == a[4].values
    cfg = c.episode_config(index=3, seed=a[3].seed, values=a[3].values)
    assert cfg.mode.value == "lockstep" and cfg.seed == a[3].seed and cfg.name == "t-e00003"
    assert cfg.scenario.params["gap_m"] == a[3].values["gap_m"]
    assert cfg.lockstep.latency.kind.value == "normal" and cfg.lockstep.latency.std_ms == a[3].values["latency.std_ms"]


def test_lockstep_episodes_open_no_corner_case_for_wall_clock_timing_anomalies():
    # A base that asks for timing-anomaly cases: in a lockstep episode they could never
    # be replayed and would depend on the machine's load (and so on the sharding).
    c = spec(run={**BASE["run"], "corner_cases": {"on_anomalies": ["deadline_miss", "latency_spike"]}})
    d = draw_generation(c, 0)[0]
    cfg = c.episode_config(index=0, seed=d.seed, values=d.values)
    assert cfg.corner_cases.on_anomalies == [] and cfg.corner_cases.enabled


def test_default_space_is_the_whole_scenario_and_integers_stay_whole():
    c = spec(params=None, latency={}, run={"mode": "lockstep", "scenario": {"name": "multi_vehicle"}})
    names = [d.name for d in c.dims]
    assert names == ["n_vehicles", "speed_mps", "headway_m", "main_start_m", "cross_start_m", "crossing_share"]
    ns = [d.values["n_vehicles"] for g in range(3) for d in draw_generation(c, g)]
    p = next(p for p in scenario_def("multi_vehicle").params if p.name == "n_vehicles")
    assert all(float(n).is_integer() and p.lo <= n <= p.hi for n in ns) and len(set(ns)) > 5


def test_shard_slices_are_disjoint_and_cover_the_campaign():
    for n in range(1, 6):
        owners = [[s for s in range(n) if Shard(s, n).owns(i)] for i in range(37)]
        assert all(len(o) == 1 for o in owners)
    assert parse_shard("1/3") == Shard(1, 3) and parse_shard(" 0 / 1 ") == Shard(0, 1)


@pytest.mark.parametrize("text,msg", [("3/2", "index 3 out of range; expected 0 <= i < 2"),
                                      ("2/2", "out of range"), ("0/0", "N = 0; expected at least 1"),
                                      ("-1/2", "out of range"), ("a/b", "expected i/N"), ("1", "expected i/N")])
def test_bad_shard_specs(text, msg):
    with pytest.raises(ConfigError, match=msg.replace("(", r"\(")):
        parse_shard(text)


@pytest.mark.parametrize("over,msg", [
    ({"params": {"gap_m": [60, 60]}}, "params.gap_m: empty range [60, 60]; expected lo < hi within [15, 150] m"),
    ({"params": {"gap_m": [70, 20]}}, "params.gap_m: empty range [70, 20]"),
    ({"latency": {"ms": [100, 100]}}, "latency.ms: empty range [100, 100]"),
    ({"params": {"gap_m": [5, 60]}}, "params.gap_m: range [5, 60] leaves the space [15, 150] m"),
    ({"params": {"gap_m": [20]}}, "params.gap_m: got [20.0]; expected a range"),
    ({"params": {"speed": [1, 2]}}, "params.speed: unknown parameter of scenario 'stopped_car'; valid: gap_m"),
    ({"latency": {"drop": [0, 0.1]}}, "latency.drop: not a searchable latency field"),
    ({"latency": {"kind": "recorded", "ms": [0, 9]}}, "latency.kind: got 'recorded'"),
    ({"episodes": 0}, "spec error at episodes: got 0"),
    ({"strategy": {"kind": "annealing"}}, "spec error at strategy.kind"),
    ({"bogus": 1}, "unknown key 'bogus'"),
    ({"params": {}, "latency": {}}, "nothing to search"),
])
def test_bad_spec_is_one_clear_error(over, msg):
    with pytest.raises(ConfigError) as info:
        spec(**over)
    assert msg in str(info.value) and str(info.value).startswith("t.yaml")
    assert "\n" not in str(info.value)


def test_campaign_id_names_the_resolved_spec(tmp_path):
    a, b = spec(), spec()
    assert a.campaign_id == b.campaign_id and len(a.campaign_id) == 16
    assert spec(episodes=25).campaign_id != a.campaign_id
    assert spec(run={**BASE["run"], "duration_s": 3.0}).campaign_id != a.campaign_id
    # The shipped spec loads (its base is found next to it) and overrides apply.
    c = load_spec(ROOT / "hil_configs" / "search.yaml", overrides=["duration_s=2"], episodes=5, strategy="mutate")
    assert c.episodes == 5 and c.strategy.kind.value == "mutate" and c.run["duration_s"] == 2.0
    assert c.run["target"]["command"][-1] == "hil.targets.cv_baseline"


def test_guided_generations_concentrate_on_the_worst_episodes():
    c = spec(strategy={"kind": "cem", "generation": 8, "explore": 0.25, "sigma": 0.05})
    gen0 = draw_generation(c, 0)
    assert {d.origin for d in gen0} == {"random"}
    assert all(d.origin.startswith("random (no signal") for d in draw_generation(c, 1, []))
    hot = np.array([0.2, 0.8, 0.5, 0.3])
    history = [Past(d.index, tuple(d.unit), 0.0) for d in gen0]
    history[2] = Past(2, tuple(hot), 10.0)
    history[5] = Past(5, tuple(hot + 0.02), 9.0)
    gen1 = draw_generation(c, 1, history)
    assert gen1 == draw_generation(c, 1, list(reversed(history)))  # deterministic in the history
    guided = [d for d in gen1 if d.origin.startswith("cem")]
    assert len(guided) == 6 and sum(d.origin == "explore" for d in gen1) == 2
    units = np.array([d.unit for d in guided])
    assert np.all(np.abs(units.mean(axis=0) - hot) < 0.12)
    # History of later generations is not used.
    assert draw_generation(c, 1, [*history, Past(9, (0.9,) * 4, 50.0)]) == gen1
    m = spec(strategy={"kind": "mutate", "generation": 8, "explore": 0.0, "sigma": 0.02})
    kids = draw_generation(m, 1, history)
    assert {d.origin.split(" ")[1] for d in kids} == {"e00002", "e00005"}
    assert all(np.max(np.abs(np.array(d.unit) - hot)) < 0.2 for d in kids)


def test_score_weights_what_went_wrong():
    assert score(mismatches={}, collided_egos=0, min_gaps_m=[None, 40.0], near_miss_m=5) == 0
    s = score(mismatches={"collision_while_safe/perception": 1, "state_mismatch/latency": 2}, collided_egos=1,
              min_gaps_m=[0.0], near_miss_m=5)
    assert s == 10 + 6 + 5 + 2
    assert score(mismatches={}, collided_egos=0, min_gaps_m=[2.5], near_miss_m=5) == 1.0


def test_cli_bad_input_is_one_line_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("run: {mode: lockstep}\nparams: {gap_m: [40, 40]}\n")
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))

    def hil(*args):
        return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "search", *args], cwd=ROOT, capture_output=True,
                              text=True, timeout=120, env=env, check=False)

    for args, msg in [((str(bad),), "params.gap_m: empty range [40, 40]"),
                      ((str(ROOT / "hil_configs/search.yaml"), "--shard", "3/2"), "--shard 3/2: index 3 out of range"),
                      ((str(ROOT / "hil_configs/search.yaml"), "--shard", "0/0"), "--shard 0/0: N = 0"),
                      ((str(tmp_path / "none.yaml"),), "campaign spec not found"),
                      (("merge", str(tmp_path / "m"), str(tmp_path / "nope")), "no such campaign folder")]:
        p = hil(*args, "--out", str(tmp_path / "out")) if args[0] != "merge" else hil(*args)
        assert p.returncode == 2, (args, p.stdout, p.stderr)
        assert msg in p.stderr and "Traceback" not in p.stderr and p.stderr.count("\n") == 1, p.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "m").exists()
    taken = tmp_path / "taken"  # refused before the campaign's line is printed (it came first)
    taken.mkdir()
    (taken / "notes.txt").write_text("mine")
    p = hil(str(ROOT / "hil_configs/search.yaml"), "--out", str(taken))
    assert p.returncode == 2 and "not empty and holds no campaign" in p.stderr and p.stdout == "", (p.stdout, p.stderr)
    p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "--help"], cwd=ROOT, capture_output=True, text=True,
                       check=False)
    assert "search" in p.stdout


def test_the_kubernetes_manifest_runs_the_search_command_for_each_index():
    import yaml

    docs = list(yaml.safe_load_all((ROOT / "deploy" / "search-job.yaml").read_text()))
    job = next(d for d in docs if d["kind"] == "Job")
    spec_ = job["spec"]
    assert spec_["completionMode"] == "Indexed" and spec_["template"]["spec"]["restartPolicy"] == "Never"
    (ctr,) = spec_["template"]["spec"]["containers"]
    env = {e["name"]: e.get("value") for e in ctr["env"]}
    assert int(env["SHARDS"]) == spec_["completions"]
    from hil.harness.search.cli import run_parser

    seen = []
    for i in range(spec_["completions"]):
        subst = {"JOB_COMPLETION_INDEX": str(i), **{k: v for k, v in env.items() if v is not None}}
        argv = [a for a in ctr["command"] + ctr["args"]]
        for k, v in subst.items():
            argv = [a.replace(f"$({k})", v) for a in argv]
        assert argv[:2] == ["hil", "search"] and "$(" not in " ".join(argv)
        args = run_parser().parse_args(argv[2:])
        assert (ROOT / args.spec).is_file() and args.resume and args.workers == int(env["WORKERS"])
        seen.append((parse_shard(args.shard), str(args.out)))
    assert [s for s, _ in seen] == [Shard(i, spec_["completions"]) for i in range(spec_["completions"])]
    assert len({o for _, o in seen}) == len(seen)  # one folder per slice
    merge_job = yaml.safe_load((ROOT / "deploy" / "merge-job.yaml").read_text())
    assert "hil search merge /data/merged /data/shard-*" in merge_job["spec"]["template"]["spec"]["containers"][0][
        "command"][-1]
