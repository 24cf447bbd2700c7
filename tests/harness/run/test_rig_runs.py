"""Camera rigs in real runs (issue 31): a rig's frames go to the target as frame sets
(PROTOCOL.md 4.2.1) and are measured camera by camera; injected faults (a slow
camera at the target, a camera that never triggers, a trigger offset) are each
flagged once, naming what they are about."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from hil.harness.config.loading import parse_config
from hil.harness.run.driver import RunResult, execute, prepare_out_dir
from tests.conftest import GL_BACKEND, read_mcap

SURROUND = ("front", "front_left", "front_right", "back", "back_left", "back_right")


def run(tmp: Path, *echo: str, **cfg: Any) -> tuple[RunResult, dict[str, list[Any]]]:
    base: dict[str, Any] = {"mode": "lockstep", "duration_s": 1.0, "progress": False, "seed": 3,
                            "camera": {"rig": "surround6", "fps": 10}, "recording": {"images": False},
                            "detector": {"enabled": False},
                            "target": {"command": [sys.executable, "-m", "hil.targets.echo", *echo]}}
    for k, v in cfg.items():
        base[k] = {**base.get(k, {}), **v} if isinstance(v, dict) else v
    r = execute(parse_config(base), out_dir=prepare_out_dir(tmp / "run"), gl_backend=GL_BACKEND,
                install_signal_handlers=False)
    return r, read_mcap(r.mcap_path)


def events(m: dict[str, list[Any]], kind: str) -> list[dict[str, Any]]:
    return [d for _, d in m.get("/events", []) if d["kind"] == kind]


@pytest.fixture(scope="module")
def sets(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunResult, dict[str, list[Any]]]:
    return run(tmp_path_factory.mktemp("sets"), "--cameras", "set")


def test_surround6_goes_as_complete_frame_sets_with_capture_skew_exactly_zero(sets: Any) -> None:
    r, m = sets
    recs = [d for _, d in m["/ego0/pipeline"]]
    assert len(recs) == 60 and all(d["status"] == "ok" for d in recs)
    assert sorted(d["frame_id"] for d in recs) == list(range(60))  # consecutive ids, camera order
    for d in recs:
        assert d["camera"] == d["frame_id"] % 6
        assert d["sim_time_ns"] == (d["frame_id"] // 6) * 100_000_000  # one instant per set
    by_set: dict[int, set[int]] = {}
    for d in recs:
        by_set.setdefault(d["frame_id"] // 6, set()).add(d["t_state_ns"])
    assert all(len(t) == 1 for t in by_set.values())  # one capture instant each
    # The target assembled every set whole: one ESTIMATE per set, SAFE (not SLOW: none
    # missing), an object from each of the six cameras.
    est = [d for _, d in m["/ego0/estimate"]]
    assert [d["frame_id"] for d in est] == list(range(0, 60, 6))
    assert all(d["state"] == "SAFE" and len(d["objects"]) == 6 for d in est)
    v = r.summary["vehicles"]["ego0"]
    rig = v["rig"]
    assert (rig["sets"], rig["complete"], rig["capture_skew_ms_max"]) == (10, 10, 0.0)
    assert list(v["cameras"]) == list(SURROUND) and all(c["frames"] == 10 for c in v["cameras"].values())
    assert not {"rig_desync", "camera_missing", "camera_late"} & set(v["anomalies"])


def test_one_slow_camera_is_camera_late_once_naming_it(tmp_path: Path) -> None:
    r, m = run(tmp_path, "--cameras", "each", "--camera-delay-ms", "5:60")
    (ev,) = events(m, "camera_late")
    assert "back_right" in ev["detail"] and ev["measured"] > 20
    assert r.summary["vehicles"]["ego0"]["anomalies"]["camera_late"] == 1
    assert not events(m, "camera_missing") and not events(m, "rig_desync")


def test_a_camera_that_never_triggers_is_camera_missing_once_and_its_ids_stay_unused(tmp_path: Path) -> None:
    r, m = run(tmp_path, "--cameras", "set", engine={"faults": {"drop_camera": "back"}})
    (ev,) = events(m, "camera_missing")
    assert "back" in ev["detail"] and ev["frame_ids"] == [0, 1, 2, 4, 5]
    ids = {d["frame_id"] for _, d in m["/ego0/pipeline"]}
    assert ids == {f for f in range(60) if f % 6 != 3}
    # The target gave each set up without camera 3 (SLOW: incomplete) and answered it.
    assert all(d["state"] == "SLOW" and len(d["objects"]) == 5 for _, d in m["/ego0/estimate"])
    v = r.summary["vehicles"]["ego0"]
    assert v["cameras"]["back"]["missing_in_sets"] == 10 and v["rig"]["complete"] == 0


def test_a_trigger_offset_in_real_time_is_rig_desync_once(tmp_path: Path) -> None:
    rig = [{"name": "front"}, {"name": "left", "yaw_deg": 60}, {"name": "right", "yaw_deg": -60, "offset_ms": 10}]
    r, m = run(tmp_path, "--cameras", "set", mode="realtime", duration_s=2.0, camera={"rig": rig},
               target={"estimate_timeout_s": 0.5})
    (ev,) = events(m, "rig_desync")
    assert ev["frame_ids"][:2] == [0, 1] and ev["threshold"] == 1.0
    skew = r.summary["vehicles"]["ego0"]["rig"]["capture_skew_ms_max"]
    assert 9.0 < skew < 20.0, skew  # the 10 ms offset, give or take the physics's step lateness
    recs = [d for _, d in m["/ego0/pipeline"] if d["camera"] == 2]
    assert all(d["t_state_ns"] > 0 for d in recs)


def test_a_target_without_cap_cameras_gets_camera_0_only_and_is_told_once(tmp_path: Path) -> None:
    r, m = run(tmp_path)
    recs = [d for _, d in m["/ego0/pipeline"]]
    # Camera 0 as a single camera: records without a camera, no frame sets judged, so
    # the five cameras it never gets are no camera_missing (a demo target on a rig
    # config failed its anomaly check on that).
    assert [d["frame_id"] for d in recs] == list(range(10)) and not any("camera" in d for d in recs)
    (ev,) = events(m, "rig_camera_zero_only")
    assert "CAP_CAMERAS" in ev["detail"] and "front" in ev["detail"]
    v = r.summary["vehicles"]["ego0"]
    assert "rig" not in v and "cameras" not in v and not events(m, "camera_missing"), v.get("anomalies")
    assert v["estimates_applied"] == 10
    from hil.harness.cli.main import link_warnings  # the terminal's line, from the summary
    from hil.harness.vocab.figures import RunFigures

    (line,) = link_warnings(RunFigures.from_json(r.summary), rig_cameras=6)
    assert line.startswith("ego0:") and "camera 0 only of the 6-camera rig" in line
