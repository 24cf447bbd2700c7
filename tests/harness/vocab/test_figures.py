"""``summary.json`` as typed figures (issue 27 item 1): every figure of a real run's
summary reads back as written (today's run and one recorded by an older harness),
a minimal old summary reads with the documented defaults, and a malformed field is
one line naming it (exit 2 from the CLI)."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

from hil.common.errors import ConfigError
from hil.harness.cli.main import main as hil_main
from hil.harness.config.loading import parse_config
from hil.harness.record.run_folder import load_figures, read_run
from hil.harness.run.driver import execute, prepare_out_dir
from hil.harness.vocab.figures import RunFigures, StageFigures
from hil.harness.vocab.verdict import verdict_json
from tests.conftest import GL_BACKEND

OLD = Path(__file__).parents[1] / "record" / "fixtures" / "run_before_orjson"


@pytest.fixture(scope="module")
def run_now(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The fixture's own short lockstep run (its config.json), made by this build."""
    cfg = json.loads((OLD / "config.json").read_text())
    cfg.update(progress=False)
    cfg["target"]["command"] = [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.2"]
    out = prepare_out_dir(tmp_path_factory.mktemp("figures") / "run")
    execute(parse_config(cfg), out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    return out


def _agrees(record: Any, written: Any, path: str) -> None:
    """Every field of ``record`` is what ``written`` holds under its name (same value,
    same JSON type), and its ``extra`` is exactly the rest."""
    if dataclasses.is_dataclass(record):
        assert isinstance(written, Mapping), path
        names = {f.name for f in dataclasses.fields(record)}
        for name in names:
            value = getattr(record, name)
            if name == "extra":
                assert value == {k: v for k, v in written.items() if k not in names}, path
            elif name == "stage_p50_ms":  # a rig camera's <stage>_p50_ms keys
                assert {f"{k}_p50_ms": v for k, v in value.items()} == {
                    k: v for k, v in written.items() if k.endswith("_p50_ms")}, path
            elif name in written:
                _agrees(value, written[name], f"{path}.{name}")
        return
    if isinstance(record, tuple):
        assert isinstance(written, list) and len(record) == len(written), path
        for i, (r, w) in enumerate(zip(record, written)):
            _agrees(r, w, f"{path}[{i}]")
        return
    if isinstance(record, Mapping):
        assert isinstance(written, Mapping) and list(record) == list(written), path  # the file's order
        for k in record:
            _agrees(record[k], written[k], f"{path}.{k}")
        return
    assert record == written and type(record) is type(written), (path, record, written)


def test_every_figure_of_todays_run_reads_back_as_written(run_now: Path) -> None:
    written = json.loads((run_now / "summary.json").read_text())
    f = RunFigures.from_json(written)
    _agrees(f, written, "summary")
    assert f.verdict.to_json() == written["verdict"]
    v = f.vehicles["ego0"]
    assert v.frames_sent == written["vehicles"]["ego0"]["frames_sent"] > 0 and v.clock is not None
    assert v.budgets is not None and v.budgets["end_to_end"].frames == v.latency_ms["end_to_end"].count
    for stage, st in v.latency_ms.items():
        assert st.to_json() == written["vehicles"]["ego0"]["latency_ms"][stage]
    # The sections no reader takes apart are kept whole.
    assert set(v.extra) == {"streaming_ms", "splits_ms", "splits_excluded", "capture_to_send_parts_ms"}
    assert {"scenario_realized", "spill", "session"} <= set(f.extra) and f.realtime is not None
    assert set(f.realtime.extra) == {"lateness_histogram"}
    # What the run folder reader and the report read is the same record.
    assert read_run(run_now).summary == f == load_figures(run_now)


def test_a_summary_recorded_by_an_older_harness_reads_back_as_written() -> None:
    written = json.loads((OLD / "summary.json").read_text())
    f = RunFigures.from_json(written)
    _agrees(f, written, "summary")
    assert f.verdict.to_json() == written["verdict"]
    assert f.completed and f.vehicles["ego0"].latency_ms["end_to_end"].p99_ms == 16.7936
    # It has no frames_accounted, rig or shards: the documented defaults.
    assert f.vehicles["ego0"].frames_accounted == f.vehicles["ego0"].frames_sent == 20
    assert f.vehicles["ego0"].rig is None and f.realtime is not None and f.realtime.shards is None


def test_a_minimal_old_summary_reads_with_the_documented_defaults() -> None:
    old = {"schema_version": 1, "ended_by": "duration", "vehicles": {"ego0": {
        "frames_sent": 50, "dropped": 2, "latency_ms": {"end_to_end": {"count": 48, "p50_ms": 10, "p99_ms": 21.5},
                                                        "transport": {"count": 0}}}}}
    f = RunFigures.from_json(old)
    v = f.vehicles["ego0"]
    assert (v.frames_sent, v.frames_accounted, v.dropped, v.stale, v.late_frames) == (50, 50, 2, 0, 0)
    assert v.drop_rate is None and v.budgets is None and v.clock is None and v.target is None
    assert v.latency_ms["end_to_end"] == StageFigures(48, p50_ms=10, p99_ms=21.5)
    assert type(v.latency_ms["end_to_end"].p50_ms) is int  # printed as written
    assert v.latency_ms["transport"].to_json() == {"count": 0}
    assert f.realtime is None and f.recorder is None and f.collisions == () and f.name is None
    # No verdict in it: rebuilt from its figures, as verdict_of does.
    assert f.verdict.to_json() == verdict_json(old)
    drop = f.verdict.check("drop")
    assert drop is not None and not drop.ok and drop.headline == "dropped: ego0: 2 of 50 frames got no estimate in time"
    assert f.verdict.failed == ("drop",) and not f.verdict.passed


@pytest.mark.parametrize(("where", "value", "field"), [
    (("vehicles", "ego0", "dropped"), "two", "vehicles.ego0.dropped: expected an integer, got 'two'"),
    (("vehicles", "ego0", "latency_ms", "end_to_end", "p99_ms"), [1], "vehicles.ego0.latency_ms.end_to_end.p99_ms"),
    (("vehicles", "ego0", "clock"), 3, "vehicles.ego0.clock: expected an object, got 3"),
    (("realtime", "lagging"), "physics", "realtime.lagging: expected a list of strings"),
    (("verdict", "checks", 1, "ok"), "yes", "verdict.checks[1].ok: expected true or false"),
    (("ended_by",), 7, "ended_by: expected a string or null, got 7"),
    (("vehicles",), [], "vehicles: expected an object, got []"),
])
def test_a_malformed_field_is_one_line_naming_it(where: tuple[Any, ...], value: Any, field: str) -> None:
    d = copy.deepcopy(json.loads((OLD / "summary.json").read_text()))
    at = d
    for k in where[:-1]:
        at = at[k]
    at[where[-1]] = value
    with pytest.raises(ConfigError) as err:
        RunFigures.from_json(d)
    assert str(err.value).startswith(field) and "\n" not in str(err.value)


def test_the_cli_names_the_file_and_the_field_and_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "run"
    shutil.copytree(OLD, folder)
    d = json.loads((folder / "summary.json").read_text())
    d["vehicles"]["ego0"]["budgets"]["end_to_end"]["over"] = "none"
    (folder / "summary.json").write_text(json.dumps(d))
    for argv in (["report", str(folder)], ["compare", str(OLD), str(folder)]):
        assert hil_main(argv) == 2
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(err) == 1 and "Traceback" not in err[0], err
        assert (f"{folder / 'summary.json'}: not a run summary: vehicles.ego0.budgets.end_to_end.over: "
                "expected an integer, got 'none'") in err[0], argv
