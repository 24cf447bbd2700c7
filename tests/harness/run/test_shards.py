"""Shards of vehicles in processes of their own (issue 24, engine.shards): one run
still gives one run folder with today's channels; in lockstep the truth and the
estimates are the same to the byte, channel by channel, as with every vehicle in the
run process; events counted by the run's bus equal /events; every process ends."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hil.common.errors import ConfigError
from hil.harness.config.loading import parse_config
from hil.harness.run.driver import execute, prepare_out_dir
from hil.harness.run.fleet import assign, shard_count
from tests.conftest import GL_BACKEND, read_mcap, recording_started

ROOT = Path(__file__).resolve().parents[3]
ECHO = [sys.executable, "-m", "hil.targets.echo", "--throttle", "0.2"]


def _cfg(**extra: object) -> dict[str, object]:
    cfg: dict[str, object] = {
        "name": "shards", "mode": "lockstep", "duration_s": 1.5, "progress": False, "seed": 4,
        "camera": {"fps": 10.0},
        "scenario": {"name": "multi_vehicle", "params": {"n_vehicles": 4}},
        "target": {"command": ECHO, "estimate_timeout_s": 10.0}}
    cfg.update(extra)
    return cfg


def _run(tmp: Path, shards: int, **extra: object):
    cfg = parse_config({**_cfg(**extra), "engine": {"shards": shards}})
    return execute(cfg, out_dir=prepare_out_dir(tmp / f"s{shards}"), gl_backend=GL_BACKEND,
                   install_signal_handlers=False)


def _children(pid: int) -> set[int]:
    """Every descendant of ``pid`` but multiprocessing's resource tracker and the
    engine's fork server (each one per test process, started by the first run, living
    as long as the tests)."""
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True, check=False)
    kids = {int(x) for x in out.stdout.split()}
    for k in list(kids):
        kids |= _children(k)
    return {k for k in kids if not any(m in _cmdline(k) for m in (b"resource_tracker", b"forkserver import main"))
            or _is_fork_of_server(k)}


def _is_fork_of_server(pid: int) -> bool:
    """An engine child (a fork of the fork server, so with its command line)."""
    try:
        ppid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return False
    return b"forkserver import main" in _cmdline(ppid)


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("shards")
    before = _children(os.getpid())
    one, two = _run(root, 1), _run(root, 2)
    left = _children(os.getpid()) - before
    return one, two, left


def test_two_shards_record_what_one_does_to_the_byte(pair) -> None:
    one, two, _left = pair
    assert two.summary["realtime"]["shards"] == 2 and one.summary["realtime"]["shards"] == 1
    a, b = read_mcap(one.mcap_path), read_mcap(two.mcap_path)
    assert set(a) == set(b)  # today's channels, one run.mcap
    timed = ("/events", "/log", "/clock", "/clock_sync")  # what depends on the machine's timing
    for topic in a:
        if not topic.endswith(timed):
            assert len(a[topic]) == len(b[topic]), topic
        if topic == "/ground_truth" or topic.endswith(("/truth", "/estimate")):
            assert [m.data for m, _ in a[topic]] == [m.data for m, _ in b[topic]], topic
    for name in ("ego0", "ego1", "ego2", "ego3"):
        assert [d["frame_id"] for _, d in b[f"/{name}/pipeline"]] == list(range(15))
        for cam in (a[f"/{name}/camera"][0][0].data, b[f"/{name}/camera"][0][0].data):  # the same JSON image
            assert cam.startswith(b'{"timestamp":{"sec":') and b'"format":"jpeg","data":"/9j/' in cam
        va, vb = one.summary["vehicles"][name], two.summary["vehicles"][name]
        assert vb["frames_sent"] == va["frames_sent"] == 15 and vb["estimates_applied"] == 15
        assert vb["outcome"] == va["outcome"]
        assert {k: n for k, n in vb["events"].items() if k.startswith("mismatch.")} == \
            {k: n for k, n in va["events"].items() if k.startswith("mismatch.")}  # timing anomalies may differ
        assert vb["target"]["name"] == "echo"
    for s in (one.summary, two.summary):  # the bus's counts are exactly what /events holds
        counts: dict[str, dict[str, int]] = {}
        for _, d in (read_mcap(one.mcap_path) if s is one.summary else b).get("/events", []):
            by = counts.setdefault(d["vehicle"] or "", {})
            by[d["kind"]] = by.get(d["kind"], 0) + 1
        for name, v in s["vehicles"].items():
            assert v["events"] == counts.get(name, {}), name
    assert (two.out_dir / "summary.json").exists() and (two.out_dir / "report.html").exists()


def test_capture_to_send_parts_add_up_to_it_in_and_out_of_process(pair) -> None:
    # Every frame was applied (15 of 15), so the parts and capture -> send cover the
    # same frames: their means add up (to the summary's rounding), and none is negative.
    one, two, _left = pair
    for s in (one.summary, two.summary):
        for name, v in s["vehicles"].items():
            parts, c2s = v["capture_to_send_parts_ms"], v["latency_ms"]["capture_to_send"]
            assert list(parts) == ["encode", "hand_off", "queue", "send"], name
            assert all(p["count"] == v["frames_sent"] == c2s["count"] for p in parts.values()), name
            assert all(p["min_ms"] >= 0 for p in parts.values()), (name, parts)
            assert sum(p["mean_ms"] for p in parts.values()) == pytest.approx(c2s["mean_ms"], abs=3e-4), name
            assert parts["encode"]["p50_ms"] > 0.01, name  # a JPEG is encoded in the worker, not in no time


def test_a_shard_process_reads_its_first_frames_at_once(pair) -> None:
    # A shard builds its vehicles' work before the run starts: built after it, every
    # vehicle's first frame waited in the render pipe for the shard's imports (0.2-0.3 s
    # here, growing with the vehicles of the shard), which at 20 fps is a burst of late
    # frames at every run's start.
    _one, two, _left = pair
    first = {name: d["t_tx_ns"] - d["t0_ns"] for name in ("ego0", "ego1", "ego2", "ego3")
             for _, d in read_mcap(two.mcap_path)[f"/{name}/pipeline"] if d["frame_id"] == 0}
    assert len(first) == 4 and max(first.values()) < 100e6, first


def test_shard_processes_and_their_targets_end_with_the_run(pair) -> None:
    _one, _two, left = pair
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(Path(f"/proc/{k}").exists() for k in left):
        time.sleep(0.1)  # a zombie reaped late is no orphan; wait a little for the reaper
    assert not [_cmdline(k)[:200] for k in left if Path(f"/proc/{k}").exists()]


@pytest.mark.slow
def test_a_sharded_real_time_run_keeps_every_frame_accounted(tmp_path: Path) -> None:
    r = _run(tmp_path, 2, mode="realtime", duration_s=2.0)
    assert r.summary["ended_by"] == "duration"
    for name, v in r.summary["vehicles"].items():
        assert v["frames_sent"] >= 15, name
        assert v["estimates_applied"] + v["dropped"] + v["stale"] == v["frames_sent"], name
        assert v["latency_ms"]["end_to_end"]["count"] > 0 and v["clock"]["samples_used"] > 0, name
    cost = r.summary["harness_cost"]
    assert cost["run_us_per_frame"] > 0
    # Where the CPU went, the shards' threads too (summed over both), all within the
    # run-side total (which counts both shard processes whole).
    threads = cost["threads_us_per_frame"]
    assert {"loop", "mcap-writer", "shard:loop", "shard:hil-analysis", "shard:local-rx"} <= set(threads), threads
    assert all(us >= 0 for us in threads.values()) and sum(threads.values()) <= cost["run_us_per_frame"], cost
    # The four cameras trigger at different instants: /ground_truth has each instant,
    # the Foxglove views of the world (/scene, world -> vehicle on /tf) one per camera
    # period (they were one per instant: N per period, N^2 messages a period).
    m = read_mcap(r.mcap_path)
    truths = {d["sim_time_ns"] for _, d in m["/ground_truth"]}
    scenes = [d for _, d in m["/scene"]]
    periods = {t // 100_000_000 for t in truths}  # 10 fps
    assert len(truths) >= 3.5 * len(periods) and len(scenes) == len(periods), (len(truths), len(scenes))
    to_vehicles = [d for _, d in m["/tf"] if d["parent_frame_id"] == "world"]
    assert len(to_vehicles) == 4 * len(scenes)


def test_how_many_shards() -> None:
    cfg = parse_config(_cfg())
    assert shard_count(cfg, 1, cores=2) == 1  # N=1 never pays for a process
    assert shard_count(cfg, 16, cores=2) == 1  # 2 cores have none to spare
    assert shard_count(cfg, 64, cores=16) == 4 and shard_count(cfg, 64, cores=64) == 4
    assert shard_count(cfg, 8, cores=64) == 1 and shard_count(cfg, 16, cores=16) == 1
    assert shard_count(cfg, 17, cores=16) == 2 and shard_count(cfg, 24, cores=16) == 2  # one shard of 24 saturated
    assert shard_count(parse_config({**_cfg(), "engine": {"shards": 3}}), 2) == 2  # at most one per vehicle
    assert assign(5, 2) == (0, 1, 0, 1, 0) and assign(5, 1) == ()
    can = parse_config({**_cfg(), "target": {"transport": "can"}, "engine": {"shards": 2}})
    with pytest.raises(ConfigError, match="engine.shards: 2 .* transport can"):
        shard_count(can, 4)
    assert shard_count(parse_config({**_cfg(), "target": {"transport": "can"}}), 64, cores=64) == 1


@pytest.mark.slow
def test_sigterm_ends_a_sharded_run_cleanly(tmp_path: Path) -> None:
    out = tmp_path / "run"
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    p = subprocess.Popen([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/scale.yaml", "--no-progress",
                          "--out", str(out), "--set", "scenario.params.n_vehicles=4", "--set", "duration_s=60",
                          "--set", "engine.shards=2", "--set", 'target.command=["{python}", "-m", "hil.targets.echo"]'],
                         cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and not (out / "run.mcap").exists():
            time.sleep(0.2)
        kids = _children(p.pid)
        shards = [k for k in kids if b"spawn_main" in _cmdline(k)]
        engine = [k for k in kids if _is_fork_of_server(k)]
        assert len(shards) == 2 and len(engine) >= 2, "two shards, physics and a render worker"
        while time.monotonic() < deadline and not recording_started(out / "run.mcap"):
            time.sleep(0.05)  # let frames flow
        p.send_signal(signal.SIGTERM)
        code = p.wait(60)
        err = p.stderr.read()
        assert code == 1 and "Traceback" not in err, err[-3000:]
        s = json.loads((out / "summary.json").read_text())
        assert "SIGTERM" in s["ended_by"] and sum(v["frames_sent"] for v in s["vehicles"].values()) > 0
        msgs = read_mcap(out / "run.mcap")
        assert msgs["/ego0/pipeline"] and msgs["/ego3/estimate"]
        end = time.monotonic() + 10
        while time.monotonic() < end and any(Path(f"/proc/{k}").exists() for k in kids):
            time.sleep(0.1)
        assert not [k for k in kids if Path(f"/proc/{k}").exists()]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)


def test_a_torn_recording_batch_stops_the_run_and_the_shard_is_still_read(tmp_path: Path) -> None:
    # A shard's recording stream that cannot be parsed (a GPU host saw one, two threads
    # of a shard sending at once): the reader thread raised and died, the shard blocked on
    # its full pipe and the run waited on it until killed. Now the run is told to stop
    # with the reason, and the pipe is read to its end. Real pipe, the handle's own reader.
    import multiprocessing as mp
    import threading

    from hil.harness.record.producer import EncodingRecorder
    from hil.harness.run.shard_handle import RemoteShard

    shard = RemoteShard.__new__(RemoteShard)  # the reader alone: no shard process
    shard.index, shard.names, shard.recorder_refused = 1, ["ego4", "ego5"], 0
    stops: list[str] = []
    shard._on_stop = stops.append
    recv, send = mp.Pipe(duplex=False)
    shard._data = recv
    written: list[str] = []

    class Rec:
        def write_encoded(self, topic: str, data: bytes, **_kw: int) -> bool:
            written.append(topic)
            return True

    reader = threading.Thread(target=shard._read_data, args=(Rec(), lambda _d, _t: None), daemon=True)
    reader.start()
    enc = EncodingRecorder(send.send_bytes)

    def shard_side() -> None:
        enc.write_json("/ego4/before", {"k": 1}, log_time_ns=1, publish_time_ns=1)
        enc.flush()
        send.send_bytes(b"\x01\x02\x03")  # shorter than a record's head
        for i in range(64):  # more than the pipe holds (~4 MB): sent only if it is read
            enc.write_raw_image("/ego4/after", np.zeros((240, 320, 3), np.uint8), encoding="rgb8", frame_id="c",
                                log_time_ns=i, publish_time_ns=i)
            enc.flush()
        send.close()

    sender = threading.Thread(target=shard_side, daemon=True)
    sender.start()
    sender.join(30)
    assert not sender.is_alive(), "the shard blocked on a pipe nobody reads"
    reader.join(30)
    assert not reader.is_alive()
    assert written == ["/ego4/before"]
    assert len(stops) == 1 and "shard 1 (ego4, ego5): its recording stream broke" in stops[0], stops
    assert "cut short at byte 0" in stops[0]
