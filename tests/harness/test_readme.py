"""The README's claims that a test can check cheaply (issue 14, item 19): every
``hil`` command line of its command list exists with every option it shows, its
example commands and overrides validate, and statements once untrue stay fixed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from hil.harness.config.model import load_config
from tests.harness.test_cli import ROOT, hil

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
