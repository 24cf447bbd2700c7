"""``hil replay`` runs the target a run folder's config.json names: a folder from
elsewhere is code, so a command that is not one of the current configs or example
targets is run only after a yes at a terminal or with --trust-config (issue 14, item 13)."""

from __future__ import annotations

import json
import sqlite3
import sys
from pathlib import Path

import pytest

from hil.harness.cases.recorder import DB_NAME, SCHEMA
from hil.harness.cases.replay_trust import check_replay_command, is_trusted
from tests.harness.test_cli import assert_one_line_error, hil
from hil.common.errors import ConfigError


def foreign_run(folder: Path, command: list[str]) -> Path:
    """A run folder as someone else could send it: one case, a config naming ``command``."""
    from hil.harness.record.recorder import Recorder

    folder.mkdir()
    with Recorder(folder / "run.mcap") as rec:  # the per-frame latencies replay applies
        rec.register_json_channel("/ego0/pipeline", "pipeline", {"type": "object"})
        for i in range(40):
            rec.write_json("/ego0/pipeline", {"frame_id": i, "status": "ok", "sim_time_ns": i * 50_000_000,
                                              "sim_time_apply_ns": i * 50_000_000 + 20_000_000},
                           log_time_ns=i + 1, publish_time_ns=i + 1)
    (folder / "config.json").write_text(json.dumps({"name": "sent", "target": {"command": command}}))
    con = sqlite3.connect(folder / DB_NAME)
    con.execute(SCHEMA)
    con.execute("INSERT INTO cases (id, run, scenario, seed, params, config_hash, vehicle, sim_time_ns, "
                "harness_time_ns, kind, summary, event, mcap_path, messages) "
                "VALUES (1, 'sent', 'stopped_car', 0, '{}', 'x', 'ego0', 1000000000, 1, "
                "'mismatch.missed_object', 's', '{}', 'run.mcap', 0)")
    con.commit()
    con.close()
    return folder


def test_replay_refuses_a_foreign_command_without_asking_or_the_flag(tmp_path: Path):
    marker = tmp_path / "PWNED"
    run = foreign_run(tmp_path / "sent", ["/bin/sh", "-c", f"touch {marker}"])
    p = hil("replay", str(run), "1")  # stdin is not a terminal: nobody to ask
    assert_one_line_error(p, "target.command `/bin/sh -c touch", "--trust-config")
    assert not marker.exists() and not (run / "replays").exists()


def test_trusted_commands():
    assert is_trusted([])  # the target runs elsewhere: nothing is started
    assert is_trusted(["{python}", "-m", "hil.targets.cv_baseline"], ["--cruise-speed", "5"])
    assert is_trusted([sys.executable, "-m", "hil.targets.echo", "--throttle", "0.3"])
    assert is_trusted(["{python}", "-m", "hil.targets.cnn", "--detector", "cv"])
    assert not is_trusted(["{python}", "-m", "targets.nope"])
    assert not is_trusted(["{python}", "-c", "import os"])
    assert not is_trusted(["/usr/bin/python3", "-m", "hil.targets.echo"])  # another interpreter: any code


def test_a_current_configs_command_is_trusted(tmp_path: Path):
    (tmp_path / "hil_configs").mkdir()
    (tmp_path / "hil_configs" / "mine.yaml").write_text('target: {command: ["./my_ai", "--fast"], args: ["-v"]}\n')
    assert is_trusted(["./my_ai", "--fast"], ["-v"], places=[tmp_path])
    assert not is_trusted(["./my_ai", "--fast"], ["-v", "--evil"], places=[tmp_path])


def test_asking_and_the_flag():
    cfg = {"target": {"command": ["/bin/sh", "-c", "true"]}}
    asked: list[str] = []
    check_replay_command(cfg, source="r/config.json", trust=False, ask=lambda q: asked.append(q) or "y")
    assert asked and "/bin/sh -c true" in asked[0] and "[y/N]" in asked[0]
    with pytest.raises(ConfigError, match="--trust-config"):
        check_replay_command(cfg, source="r/config.json", trust=False, ask=lambda _q: "")
    check_replay_command(cfg, source="r/config.json", trust=True, ask=None)
