"""``hil replay`` runs the target a run folder's config.json names: a folder from
elsewhere is code, so a command that is not one of the current configs or example
targets is run only after a yes at a terminal or with --trust-config (issue 14, item 13).
Trust covers the options too: an example target with an option that writes (or reads) a
file is not trusted (issue 26, item 2)."""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import re
import sqlite3
import sys
from pathlib import Path

import pytest

from hil.harness.cases.casebook import DB_NAME, SCHEMA
from hil.harness.cases.replay_trust import _OPTIONS, check_replay_command, current_config_commands, is_trusted
from tests.harness.cli.test_cli import assert_one_line_error, hil
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


def test_replay_refuses_an_example_target_writing_outside_the_run_folder(tmp_path: Path):
    outside = tmp_path / "precious.txt"
    outside.write_text("keep me")
    run = foreign_run(tmp_path / "sent", ["{python}", "-m", "hil.targets.reference", "--truth", str(outside)])
    p = hil("replay", str(run), "1")
    assert_one_line_error(p, "--truth", "--trust-config")
    assert outside.read_text() == "keep me" and not (run / "replays").exists()


def test_trust_covers_the_options(tmp_path: Path):
    nowhere = [tmp_path]  # no hil_configs here: only the option table decides
    ref, cnn = ["{python}", "-m", "hil.targets.reference"], ["{python}", "-m", "hil.targets.cnn"]
    assert is_trusted(ref, ["--infer-ms", "10", "--spike-frames", "55,120", "--clock-offset-s", "-2.5"], places=nowhere)
    assert is_trusted([*cnn, "--device", "cuda:0", "--shared", "--vehicles", "0,2"], places=nowhere)
    assert is_trusted(["{python}", "-m", "hil.targets.cv_baseline", "--transport", "zenoh",
                       "--listen", "tcp/127.0.0.1:{port}", "--vehicle", "{vehicle_id}"], places=nowhere)
    for bad in (["--truth", "/tmp/x"], ["--truth=/tmp/x"], ["--tru", "/tmp/x"],  # argparse takes prefixes
                ["--name", "--truth", "/tmp/x"], ["--listen", "tcp/0.0.0.0:7447"], ["--infer-ms", "nan"],
                ["--auth-dictionary", "users.txt"], ["--tls", "listen_certificate=a.pem"], ["--once=1"],
                ["--infer-ms"], ["positional"]):
        assert not is_trusted(ref, bad, places=nowhere), bad
    for bad in (["--batch-log", "/tmp/b.csv"], ["--weights", "w"], ["--device", "cuda;rm"]):
        assert not is_trusted(cnn, bad, places=nowhere), bad
    assert not is_trusted(["{python}", "-m", "hil.targets.cnn.models"], places=nowhere)  # not a target


def test_every_shipped_config_command_passes_the_option_table(tmp_path: Path):
    commands = current_config_commands([Path(__file__).resolve().parents[3]])
    assert commands
    for command, args in commands:
        assert is_trusted(command, args, places=[tmp_path]), (command, args)


def _parser_options(module: str) -> dict[str, bool]:
    """Every option of ``module``'s real parser: name → takes a value (read from its --help usage)."""
    mod = importlib.import_module(module if module != "hil.targets.cnn" else "hil.targets.cnn.cli")
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        mod.main(["--help"])
    usage = out.getvalue().split("\n\n")[0]
    return {m[0]: bool(m[1]) for m in re.findall(r"\[(--[\w-]+)( [^\]]+)?\]", usage)}


@pytest.mark.parametrize("module", sorted(_OPTIONS))
def test_the_option_table_matches_each_targets_parser(module: str):
    real = _parser_options(module)
    for option, check in _OPTIONS[module].items():
        assert option in real, f"{module} has no {option}"
        assert real[option] == (check is not None), f"{module} {option}: flag/value mismatch"
    for writes_or_reads_a_file in ("--tls", "--auth-dictionary", "--truth", "--batch-log", "--weights"):
        assert writes_or_reads_a_file not in _OPTIONS[module]


def test_every_example_target_is_classified():
    root = Path(__file__).resolve().parents[3] / "targets"
    mains = {f"hil.targets.{p.stem}" for p in root.glob("*.py") if "def main(" in p.read_text()}
    mains |= {f"hil.targets.{p.parent.name}" for p in root.glob("*/__main__.py")}
    # The rclpy example is a ROS 2 node for users with ROS 2, not an SDK target: it stays
    # untrusted (replaying a config naming it needs --trust-config).
    assert mains - {"hil.targets.ros2_rclpy_node"} == set(_OPTIONS)
