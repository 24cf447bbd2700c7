"""A CAN run writes its bus traffic in python-can's log formats beside ``run.mcap``
(harness/record/can_log.py), on the MCAP's timeline: read back with python-can's own
readers, every clock-sync answer's frame carries the log time of its
``/<vehicle>/clock_sync`` message, and every estimate's last frame the instant of its
``t0'`` on the MCAP's wall clock."""

from __future__ import annotations

import json
import subprocess
import sys
import uuid
from pathlib import Path

import can
import numpy as np
import pytest
from mcap.reader import make_reader

from hil.harness.config.loading import load_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.adapters.can.pair import can_target
from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[3]


def _can_run(tmp_path: Path, fmt: str) -> Path:
    channel = f"hil-log-{uuid.uuid4().hex}"
    cfg = load_config(ROOT / "hil_configs/can.yaml", overrides=[
        "duration_s=1.5", "progress=false", "target.can.interface=virtual", f"target.can.channel={channel}",
        f"recording.can_log={fmt}"])
    with can_target(channel, ["--throttle", "0.1"]):
        result = execute(cfg, out_dir=prepare_out_dir(tmp_path / fmt), gl_backend=GL_BACKEND,
                         install_signal_handlers=False)
    assert result.summary["ended_by"] == "duration"
    return result.out_dir


def _mcap(run: Path) -> tuple[int, list[tuple[int, dict]], list[dict]]:
    """The time anchor's offset, /ego0/clock_sync (log time, message), /ego0/pipeline."""
    sync, pipe = [], []
    with open(run / "run.mcap", "rb") as f:
        reader = make_reader(f)
        anchor = next(m for m in reader.iter_metadata() if m.name == "time_anchor")
        for _, ch, msg in reader.iter_messages(topics=["/ego0/clock_sync", "/ego0/pipeline"]):
            d = json.loads(msg.data)
            if ch.topic == "/ego0/clock_sync":
                sync.append((msg.log_time, d))
            else:
                pipe.append(d)
    return int(anchor.metadata["log_time_offset_ns"]), sync, pipe


def _nearest_ns(times_s: np.ndarray, want_ns: list[int]) -> np.ndarray:
    """|distance| in ns from each wanted instant to the nearest logged frame time."""
    want = np.asarray(want_ns, dtype=np.float64) / 1e9
    i = np.clip(np.searchsorted(times_s, want), 1, len(times_s) - 1)
    return np.minimum(np.abs(times_s[i] - want), np.abs(times_s[i - 1] - want)) * 1e9


@pytest.mark.parametrize("fmt", ["blf", "asc"])
def test_a_can_run_logs_its_bus_traffic_on_the_mcaps_timeline(tmp_path: Path, fmt: str) -> None:
    run = _can_run(tmp_path, fmt)
    log = run / f"run.{fmt}"
    s = json.loads((run / "summary.json").read_text())
    assert s["can_log"]["file"] == log.name and s["can_log"]["dropped"] == 0 and s["can_log"]["error"] is None
    reader = can.BLFReader(str(log)) if fmt == "blf" else can.ASCReader(str(log), relative_timestamp=False)
    frames = list(reader)
    assert len(frames) == s["can_log"]["frames"] > 0
    rx = [m for m in frames if m.is_rx]
    tx = [m for m in frames if not m.is_rx]
    assert rx and tx and all(m.is_fd and m.is_extended_id for m in frames)
    assert all(m.arbitration_id & 0xFFFF == 0 for m in frames)  # vehicle 0's ids only
    offset, sync, pipe = _mcap(run)
    rx_s = np.sort([m.timestamp for m in rx])
    # Each clock-sync answer (t4: the receive stamp of its frame) is in the log at the
    # MCAP log time of its /ego0/clock_sync message: the same timestamp in both files.
    assert sync and all(log_time == d["t4_ns"] + offset for log_time, d in sync)
    assert _nearest_ns(rx_s, [log_time for log_time, _ in sync]).max() < 1000
    # Each applied estimate's receipt t0' is the stamp of its last frame.
    t0p = [d["t0p_ns"] + offset for d in pipe if d["status"] == "ok"]
    assert len(t0p) > 10 and _nearest_ns(rx_s, t0p).max() < 1000
    # Sent frames (camera frames over ISO-TP, sync requests, heartbeats) lie within the run.
    t_tx = np.array([m.timestamp for m in tx])
    first_frame = min(d["t_tx_ns"] for d in pipe) + offset
    assert t_tx.min() * 1e9 < first_frame and np.all(np.diff(t_tx) >= -1e-6)  # in the order they left
    if fmt == "blf":  # python-can's own tools read it: logconvert to ASC keeps every frame
        out = tmp_path / "converted.asc"
        p = subprocess.run([sys.executable, "-m", "can.logconvert", str(log), str(out)], capture_output=True,
                           text=True, timeout=60, check=False)
        assert p.returncode == 0, p.stderr
        assert len(list(can.ASCReader(str(out)))) == len(frames)


def test_no_log_when_asked_not_to(tmp_path: Path) -> None:
    run = _can_run(tmp_path, "none")
    assert not list(run.glob("run.blf")) and not list(run.glob("run.asc"))
    assert "can_log" not in json.loads((run / "summary.json").read_text())
