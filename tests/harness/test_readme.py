"""The README's claims that a test can check cheaply (issue 14, item 19): every
``hil`` command line of its command list exists with every option it shows, its
example commands and overrides validate, and statements once untrue stay fixed."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from hil.harness.config.loading import load_config
from tests.harness.cli.test_cli import ROOT, hil

README = (ROOT / "README.md").read_text(encoding="utf-8")


def _command_block() -> list[str]:
    block = next(b for b in README.split("```")[1::2] if b.lstrip().startswith("hil run CONFIG"))
    return [ln.split("#", 1)[0].strip() for ln in block.splitlines() if ln.strip().startswith("hil")]


def _subcommand(line: str) -> list[str]:
    words = []
    for tok in line.split()[1:]:
        if not re.fullmatch(r"[a-z][a-z-]*", tok):
            break
        words.append(tok)
    return ["target", "cv"] if words == ["target"] else words  # the options shown are the targets'


@pytest.mark.parametrize("line", _command_block())
def test_every_listed_command_takes_the_options_shown(line: str):
    sub = _subcommand(line)
    p = hil(*sub, "--help")
    assert p.returncode == 0, (line, p.stderr)
    for flag in re.findall(r"--[a-z][a-z0-9-]*", line):
        assert flag in p.stdout, (line, flag)


EXAMPLES = [  # (as the README writes it, the config, the overrides)
    ("hil run hil_configs/demo.yaml", "hil_configs/demo.yaml", []),
    ("`--set camera.fps=10`", "hil_configs/demo.yaml", ["camera.fps=10"]),
    ("`--set scenario.params.gap_m=60`", "hil_configs/demo.yaml", ["scenario.params.gap_m=60"]),
    ('`--set "scenario={name: cut_in, params: {npc_speed_mps: 14}}"`', "hil_configs/demo.yaml",
     ["scenario={name: cut_in, params: {npc_speed_mps: 14}}"]),
    ("hil run hil_configs/remote.yaml --set 'target.command=[]' \\\n"
     "    --set 'target.zenoh.connect=[\"tcp/192.168.1.50:7447\"]'", "hil_configs/remote.yaml",
     ["target.command=[]", 'target.zenoh.connect=["tcp/192.168.1.50:7447"]']),
    ("hil run hil_configs/cnn.yaml", "hil_configs/cnn.yaml", []),
    ("`hil_configs/regression.yaml` is a ready CI configuration", "hil_configs/regression.yaml",
     ["duration_s=5"]),
    ("(`hil_configs/can.yaml`)", "hil_configs/can.yaml", []),
]


@pytest.mark.parametrize(("text", "config", "overrides"), EXAMPLES)
def test_readme_examples_validate(text: str, config: str, overrides: list[str]):
    from hil import scenarios

    assert text in README, text
    cfg = load_config(ROOT / config, overrides=overrides)
    scenarios.get(cfg.scenario.name).resolve(cfg.scenario.params)
    if config.endswith("remote.yaml") and overrides:
        assert cfg.target.command == [] and cfg.target.zenoh.connect == ["tcp/192.168.1.50:7447"]


def test_cheap_readme_commands_run():
    for args in (["--version"], ["scenarios"], ["scenarios", "--json"], ["target", "--help"],
                 ["target", "echo", "--help"]):
        p = hil(*args)
        assert p.returncode == 0, (args, p.stderr)
    listed = hil("scenarios").stdout
    table = README.split("## Scenarios and ground truth")[1].split("\n## ")[0]
    names = re.findall(r"^\| `([a-z_]+)` \| ", table, flags=re.M)
    assert len(names) >= 6
    for name in names:
        assert name in listed, name


def test_statements_that_were_untrue_stay_fixed():
    assert "are planned" not in README  # zenoh, can and mixed exist
    assert "hil target cnn|cv|echo" in README
    assert "`foxglove.RawImage` with `camera.encoding: raw`" in README
    assert "world → every car, egos and scripted ones" in README
    assert "hil-1-config" not in README
    assert "--trust-config" in README and "a run folder received\nfrom someone else is code" in README


# --- issue 25, item 8: what a first contact checked and found false ------------------

SDK_README = (ROOT / "sdk" / "README.md").read_text(encoding="utf-8")


def _choices(usage: str) -> list[str]:
    """The subcommands argparse lists in a usage line (``{run,scenarios,...}``)."""
    return re.search(r"\{([a-z,-]+)\}", usage).group(1).split(",")


def test_the_synopsis_lists_every_command_and_search_subcommand():
    listed = {tuple(words) for ln in _command_block() if (words := _subcommand(ln))}
    for cmd in _choices(hil("--help").stdout):
        assert any(words[0] == cmd for words in listed), f"hil {cmd} is missing from the command list"
    search = hil("search", "--help").stdout
    for sub in re.findall(r"hil search (\w+) ", search):
        assert ("search", sub) in listed, f"hil search {sub} is missing from the command list"


def test_target_transport_is_shown_as_an_option_with_every_choice():
    line = next(ln for ln in _command_block() if ln.startswith("hil target "))
    shown = re.search(r"\[--transport ([a-z0-9|]+)\]", line)
    assert shown, line  # optional: a started target gets its transport from hil run
    offered = re.search(r"--transport \{([a-z0-9,]+)\}", hil("target", "cv", "--help").stdout).group(1)
    assert set(shown.group(1).split("|")) == set(offered.split(","))


def test_quoted_line_counts_hold():
    m = re.search(r"about (\d+) lines", SDK_README)
    assert m
    lines = sum(len(p.read_text().splitlines()) for p in (ROOT / "targets" / "c").glob("*.[ch]"))
    assert abs(lines - int(m.group(1))) <= 0.1 * lines, (m.group(1), lines)


def test_the_sdk_is_installed_from_the_wheel_the_build_writes():
    import tomllib

    assert "pip install hil-target-sdk" not in SDK_README  # on no package index
    version = tomllib.loads((ROOT / "sdk" / "pyproject.toml").read_text())["project"]["version"]
    wheel = f"dist/hil_target_sdk-{version}-py3-none-any.whl"
    assert f"python sdk/build_wheel.py                 # writes {wheel}" in SDK_README
    assert f'pip install "{wheel}[zenoh]"' in SDK_README


def test_the_gate_and_study_sentences_say_what_the_code_does():
    from hil.harness.check.gate_tolerances import Tolerances

    assert "may grow by (default)" not in README  # the allowance is not a hard limit
    tol = Tolerances()
    assert f"| `p50` | max({tol.p50.rel:.0%}, {tol.p50.abs:g} ms) |".replace("%", " %") in README
    noise = tol.noise_of("p50")
    assert f"default p50: {noise.rel:.0%} and {noise.abs:g} ms".replace("%", " %") in README
    assert "figures 7-13" not in README and "figures 7–13" not in README
    study = README.split("## Studies")[1].split("\n## ")[0]
    assert "six SVG charts" in study and "report.html" in study


def test_foxglove_steps_use_the_apps_words():
    # docs.foxglove.dev (getting started, Python): "Open connection" from the dashboard or
    # left-hand menu, then "Foxglove WebSocket" in the "Open a new connection" dialog.
    flat = " ".join(README.split())
    assert ('"Open connection" (dashboard or left-hand menu), then "Foxglove WebSocket" in the "Open a new '
            'connection" dialog') in flat
    assert "Open connection →" not in flat


def test_the_scenarios_hint_gives_overrides_that_load():
    # It said `--set scenario.name=NAME --set scenario.params.PARAM=VALUE`, which every shipped
    # config refuses (its params are its own scenario's) (README walkthrough).
    from hil import scenarios

    foot = " ".join(hil("scenarios").stdout.split("\n\n")[-1].split())
    assert "scenario.name=NAME" not in foot and "--set scenario.params.PARAM=VALUE" in foot, foot
    pick = re.search(r"--set '(scenario=\{name: NAME, params: \{PARAM: VALUE\}\})'", foot)
    assert pick, foot
    override = pick.group(1).replace("NAME", "cut_in").replace("PARAM", "npc_speed_mps").replace("VALUE", "14")
    cfg = load_config(ROOT / "hil_configs" / "demo.yaml", overrides=[override])
    assert cfg.scenario.name == "cut_in"
    scenarios.get("cut_in").resolve(cfg.scenario.params)


def test_every_summary_key_is_in_the_summary_table(tmp_path: Path):
    # `session`, `impairment`, `schema_version` and four vehicle counters were in every
    # summary.json but not in the table a tester checks it against (README walkthrough).
    from tests.scenarios.test_scenario_runs import run

    summary = run(tmp_path, mode="lockstep", duration_s=0.5).summary
    table = README.split("### `summary.json`")[1].split("\nStages")[0]
    named = set(re.findall(r"`([a-z0-9_]+)[`.]", table))  # `vehicles.<name>...` names `vehicles`
    vehicle: set[str] = set()
    for ln in (ln for ln in table.splitlines() if ln.startswith("| `vehicles.<name>")):
        cell = ln if ln.startswith("| `vehicles.<name>` |") else ln.split("|")[1]  # that row lists them after
        vehicle |= set(re.findall(r"`vehicles\.<name>\.([a-z0-9_]+)", cell) + re.findall(r"`([a-z0-9_]+)`", cell))
    assert [k for k in summary if k not in named] == []
    assert [k for k in summary["vehicles"]["ego0"] if k not in vehicle] == []


def test_the_c_target_lines_work_as_written():
    # The README named the C target but not how to build or start it (README walkthrough).
    from tests.targets import c_build

    if c_build.unavailable():
        pytest.skip(c_build.unavailable())
    flat = " ".join(README.split())
    assert "`make -C targets/c` builds `targets/c/build/hil_target`" in flat
    shown = re.search(r"serves like `hil target` \(`(--transport tcp --listen [0-9.:]+)`", flat)
    assert shown, flat
    p = subprocess.run([str(c_build.build().plain), "--help"], capture_output=True, text=True, timeout=30)
    assert p.returncode == 0 and all(opt in p.stdout for opt in shown.group(1).split() if opt.startswith("--"))


def test_the_calibrate_paragraph_names_what_it_writes():
    # `hil calibrate` had a line in the command list and nothing on what it checks or writes.
    from hil.harness.check.calibrate import TRUTH_FILE, Calibration

    para = " ".join(README.split("`hil calibrate [CONFIG]` proves")[1].split("\n\n")[0].split())
    keys = re.search(r"`calibration.json` \(([^)]*)\)", para)
    assert keys and f"`{TRUTH_FILE}`" in para, para
    written = Calibration("local").to_json()
    assert [k for k in re.findall(r"`([a-z_]+)`", keys.group(1)) if k not in written] == []
    assert (ROOT / "hil_configs" / "calibrate.yaml").is_file() and (ROOT / "targets" / "reference.py").is_file()
