"""A real rig run whose one camera is steadily slower (injected at the target, below
``camera_late``'s limit) raises no jitter, spike or reordering: the vehicle's
detectors judge each camera against its own baseline (issue 31)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import pytest

from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
from hil.timing.anomaly import AnomalyDetector, AnomalyKind, Thresholds
from hil.timing.records import FrameStatus, PipelineRecord
from tests.conftest import GL_BACKEND, read_mcap

# Camera 3 is slower by DELAY_MS, and cameras 4 and 5 wait behind it at the target:
# half the set is late by it, steadily. camera_late's limit is set over DELAY_MS / 2
# (a slow camera's excess over its set's median).
DELAY_MS = 60.0
LIMITS = {"spike_floor_ms": 25.0, "jitter_ms": 20.0}  # a loaded machine's hiccups of a few ms are neither


def _record(d: dict[str, Any], *, camera: bool) -> PipelineRecord:
    names = {f.name for f in dataclasses.fields(PipelineRecord)} - {"status", "camera"}
    return PipelineRecord(**{k: d[k] for k in names if k in d}, status=FrameStatus(d["status"]),
                          camera=d.get("camera") if camera else None)


@pytest.mark.slow
def test_a_steadily_slower_camera_raises_no_jitter_or_spike(tmp_path: Path) -> None:
    # 60 sets at 20 fps: each camera's spike baseline (50 frames) fills and is judged.
    cfg = {"mode": "lockstep", "duration_s": 3.0, "progress": False, "seed": 3, "detector": {"enabled": False},
           "timing": {"thresholds": {**LIMITS, "deadline_ms": {"end_to_end": 500}}, "rig": {"late_ms": 100}},
           "camera": {"rig": "surround6", "fps": 20, "width": 64, "height": 48}, "recording": {"images": False},
           "target": {"command": [sys.executable, "-m", "hil.targets.echo", "--cameras", "each",
                                  "--camera-delay-ms", f"3:{DELAY_MS:g}"]}}
    r = execute(parse_config(cfg), out_dir=prepare_out_dir(tmp_path / "run"), gl_backend=GL_BACKEND,
                install_signal_handlers=False)
    v = r.summary["vehicles"]["ego0"]
    cams = v["cameras"]
    assert all(c["frames"] == 60 for c in cams.values()), cams
    # The injected truth is in the figures: cameras 3 to 5 answer about DELAY_MS later than 0 to 2.
    e2e = [c["end_to_end_p50_ms"] for c in cams.values()]
    assert min(e2e[3:]) - max(e2e[:3]) > DELAY_MS / 2, cams
    m = read_mcap(r.mcap_path)
    evs = [d for _, d in m.get("/events", []) if d["kind"] in ("jitter", "latency_spike", "out_of_order")]
    # The same records as one stream (without their camera) are jitter; keyed per
    # camera they are none.
    recs = [d for _, d in m["/ego0/pipeline"]]
    one = AnomalyDetector("ego0", dataclasses.replace(Thresholds(), deadline_ms={"end_to_end": 500.0}, **LIMITS))
    as_one = [a.kind for d in recs for a in one.on_record(_record(d, camera=False))]
    assert AnomalyKind.JITTER in as_one
    # The slowness is the target's (cameras 3 to 5 wait there): no jitter, no reorder,
    # and no spike judged against another camera's baseline. A hiccup of this machine
    # on the loopback link or in the harness (a process off its core for tens of ms: a
    # fresh-clone suite saw "transport 41.2 ms" on three frames of one set) is a real
    # spike, and says its side. The target is a process of this machine too: preempted,
    # it answers a frame late (another saw camera 4's target_total 17 ms over its
    # median). Such a spike is judged against its own camera's baseline, so its limit
    # lies above that camera's steady latency; a camera judged against the faster ones'
    # baseline would have a limit below it, set after set.
    per_cam = list(cams.values())
    machine = [d for d in evs if d["kind"] == "latency_spike" and d.get("cause") in ("link", "harness")]
    preempted = [d for d in evs if d["kind"] == "latency_spike" and d.get("cause") == "target"
                 and d["threshold"] > per_cam[d["frame_ids"][0] % len(per_cam)]["end_to_end_p50_ms"]]
    rest = [d for d in evs if d not in machine and d not in preempted]
    assert not rest and len(preempted) <= 2, [(d["kind"], d["frame_ids"], d["measured"], d["threshold"], d.get("cause"),
                                               d["detail"]) for d in rest + preempted]
    assert sum(v["anomalies"].get(k, 0) for k in ("jitter", "latency_spike", "out_of_order")) == len(evs)
