"""A rig camera's delay and loss as ``hil search`` dimensions (issue 31): drawn like
any latency field, set on the episode's ``lockstep.latency.camera_ms`` /
``camera_drop_prob``, and in a real lockstep episode only that camera's controls
come later, or never."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hil.common.errors import ConfigError
from hil.harness.run.driver import execute, prepare_out_dir
from hil.harness.search.sampling import draw_generation
from hil.harness.search.spec import resolve_spec
from tests.conftest import GL_BACKEND, read_mcap

RUN = {"mode": "lockstep", "duration_s": 1.0, "progress": False, "detector": {"enabled": False},
       "recording": {"images": False}, "camera": {"rig": "surround6", "fps": 10, "width": 64, "height": 48},
       "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--cameras", "each"]}}
SPEC = {"name": "rig", "seed": 4, "episodes": 8, "run": RUN, "params": {},
        "latency": {"camera_ms.back_right": [0, 200], "camera_drop_prob.front_left": [0, 0.5]}}


def test_a_cameras_delay_and_loss_are_drawn_as_latency_dimensions() -> None:
    c = resolve_spec(SPEC, source="s.yaml")
    assert [(d.name, d.lo, d.hi, d.unit) for d in c.dims] == [
        ("latency.camera_ms.back_right", 0.0, 200.0, "ms"), ("latency.camera_drop_prob.front_left", 0.0, 0.5, "")]
    assert c.latency_kind is None  # a camera's share needs no profile: the others apply at once
    d = draw_generation(c, 0)[2]
    lat = c.episode_config(index=2, seed=d.seed, values=d.values).lockstep.latency
    assert lat.kind.value == "none" and lat.active
    assert lat.camera_ms == {"back_right": d.values["latency.camera_ms.back_right"]}
    assert lat.camera_drop_prob == {"front_left": d.values["latency.camera_drop_prob.front_left"]}


@pytest.mark.parametrize("latency,words", [
    ({"camera_ms.nope": [0, 10]}, "lockstep.latency.camera_ms.nope"),
    ({"camera_drop_prob.back": [0, 2]}, "leaves the space [0, 1]"),
    ({"cam_ms.back": [0, 10]}, "camera_ms.<camera>"),
])
def test_a_bad_camera_dimension_is_one_line_naming_it(latency: dict[str, list[float]], words: str) -> None:
    with pytest.raises(ConfigError, match=None) as err:
        resolve_spec({**SPEC, "latency": latency}, source="s.yaml")
    assert words in str(err.value) and "\n" not in str(err.value)


def test_in_an_episode_only_the_drawn_camera_is_late_or_lost(tmp_path: Path) -> None:
    c = resolve_spec(SPEC, source="s.yaml")
    # The last camera is the late one: no newer frame of its set is applied before it
    # (an earlier camera's late control would be stale, as in real time).
    cfg = c.episode_config(index=0, seed=3, values={"latency.camera_ms.back_right": 40.0,
                                                    "latency.camera_drop_prob.front_left": 0.5})
    r = execute(cfg, out_dir=prepare_out_dir(tmp_path / "run"), gl_backend=GL_BACKEND, install_signal_handlers=False)
    recs = [d for _, d in read_mcap(r.mcap_path)["/ego0/pipeline"]]
    late = {d["camera"]: set() for d in recs}
    for d in recs:
        if d["status"] == "ok":
            late[d["camera"]].add(d["sim_time_apply_ns"] - d["sim_time_ns"])
    assert late[5] == {40_000_000}  # back_right: 40 ms of sim time after its capture
    assert all(late[k] == {0} for k in (0, 2, 3, 4))  # the others at once
    lost = [d["status"] for d in recs if d["camera"] == 1]
    assert 0 < lost.count("dropped") < len(lost) and set(lost) <= {"ok", "dropped"}  # about half, seeded
    again = execute(cfg, out_dir=prepare_out_dir(tmp_path / "again"), gl_backend=GL_BACKEND,
                    install_signal_handlers=False)
    assert lost == [d["status"] for _, d in read_mcap(again.mcap_path)["/ego0/pipeline"] if d["camera"] == 1]
