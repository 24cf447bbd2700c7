"""The CNN target as a shared inference service (issue 18): the torch device option,
batched inference, the batching scheduler's window, fairness and timestamps, one
process serving many vehicles over the local transport, and a 4-vehicle run."""

from __future__ import annotations

import csv
import json
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from hil.adapters.batching import BatchedEndpoint, BatchLog, BatchScheduler, parse_vehicles
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import (CameraInfo, Control, DrivingState, Estimate, Frame, Hello, ImageEncoding,
                                        Inference, SyncRequest, SyncResponse)

torch = pytest.importorskip("torch")

CAM = CameraInfo(207.846, 207.846, 160.0, 120.0, 1.3)


def _frame(vehicle_id: int, frame_id: int, *, seed: int = 0) -> Frame:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    img[150:] = 90  # a grey road below the horizon
    return Frame(vehicle_id, frame_id, 0, 0, 0, 320, 240, ImageEncoding.RGB8, CAM, 5.0, img.tobytes())


# -- device --------------------------------------------------------------------------------


def test_device_option_cpu_auto_and_refusals():
    from hil.targets.cnn.device import hello_name, parse_device

    assert parse_device("cpu").type == "cpu"
    assert parse_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("gpu", "cuda:x", "tpu:0"):
        with pytest.raises(ValueError, match="--device"):
            parse_device(bad)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            parse_device("cuda:0")
    long = hello_name("cnn", torch.device("cpu"), detail="x" * 100)
    assert long.startswith("cnn@cpu (") and len(long.encode()) == 64


def test_target_loads_its_weights_on_the_device_and_names_it():
    from hil.targets.cnn.target import CnnTarget

    t = CnnTarget(device="auto")
    want = "cuda" if torch.cuda.is_available() else "cpu"
    assert t.device.type == want and t.device_name
    assert {p.device.type for p in [*t.det_net.parameters(), *t.steer_net.parameters()]} == {want}
    assert f"device={t.device}" in t.status()


def test_bad_device_is_one_line_and_exit_2(capsys):
    from hil.targets.cnn.cli import main

    assert main(["--device", "gpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--device 'gpu'" in err[0]


def test_a_batch_answers_as_each_frame_alone():
    from hil.targets.cnn.target import CnnTarget

    torch.set_num_threads(1)
    t = CnnTarget()
    frames = [_frame(v, 10 + v, seed=v) for v in range(3)]
    alone = [t.infer(f) for f in frames]
    batch = t.infer_batch(frames)
    assert len(batch) == 3 and t.infer_batch([]) == []
    for a, b in zip(alone, batch):
        assert a.state == b.state and len(a.objects) == len(b.objects)
        assert b.control.steering_rad == pytest.approx(a.control.steering_rad, abs=1e-4)
        assert b.control.throttle == pytest.approx(a.control.throttle, abs=1e-4)


# -- the scheduler -------------------------------------------------------------------------


class _Session:
    """A real ``BatchedEndpoint`` whose transport is a list; ``got`` is set per estimate."""

    def __init__(self, sched: BatchScheduler) -> None:
        self.sent: list[object] = []
        self.got = threading.Event()
        self._cv = threading.Condition()
        self.ep = BatchedEndpoint(sched, target_name="shared-test")
        self.ep.start(self._send)

    def _send(self, buf: bytes) -> None:
        msg = protocol.decode(buf)
        with self._cv:
            self.sent.append(msg)
            self._cv.notify_all()
        if isinstance(msg, Estimate):
            self.got.set()

    def wait_estimates(self, n: int, timeout_s: float = 10.0) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: len(self.estimates()) >= n, timeout_s)

    def estimates(self) -> list[Estimate]:
        return [m for m in self.sent if isinstance(m, Estimate)]


def _answer(frames):
    return [Inference(DrivingState.SAFE, Control(0.0, f.vehicle_id / 10, 0.0), ()) for f in frames]


def test_frames_within_the_window_share_a_batch_and_keep_their_own_stamps(tmp_path: Path):
    log = BatchLog(tmp_path / "b.csv")
    sched = BatchScheduler(_answer, window_ns=5_000_000_000, max_batch=8, log=log)  # a full batch never waits 5 s
    a, b = _Session(sched), _Session(sched)
    sched.start()
    try:
        assert isinstance(a.sent[0], Hello)  # each session says its own HELLO
        a.ep.on_message(SyncRequest(0, 1, 123), t_rx=5)
        assert isinstance(a.sent[-1], SyncResponse) and a.sent[-1].t2_target_ns == 5  # answered at once
        t_a = sched.clock.now_ns()
        a.ep.on_message(_frame(0, 1), t_rx=t_a)
        t_b = sched.clock.now_ns()
        b.ep.on_message(_frame(1, 7), t_rx=t_b)
        assert a.got.wait(10) and b.got.wait(10)  # both sessions open: full at 2, no 5 s wait
    finally:
        sched.stop()
    ea, eb = a.estimates()[0], b.estimates()[0]
    assert (ea.vehicle_id, ea.frame_id, eb.vehicle_id, eb.frame_id) == (0, 1, 1, 7)
    assert ea.control.throttle == 0.0 and eb.control.throttle == pytest.approx(0.1)  # each its own answer
    assert (ea.t_rx_target_ns, eb.t_rx_target_ns) == (t_a, t_b)
    assert ea.t_infer_start_target_ns == eb.t_infer_start_target_ns and ea.t_infer_end_target_ns == eb.t_infer_end_target_ns
    for e in (ea, eb):
        assert e.t_rx_target_ns <= e.t_infer_start_target_ns <= e.t_infer_end_target_ns <= e.t_reply_target_ns
    assert sched.stats.sizes == {2: 1}
    rows = list(csv.DictReader(open(tmp_path / "b.csv")))
    assert [(r["batch"], r["batch_size"], r["vehicle_id"], r["frame_id"]) for r in rows] == [
        ("1", "2", "0", "1"), ("1", "2", "1", "7")]
    assert int(rows[0]["t_infer_start_ns"]) == ea.t_infer_start_target_ns and int(rows[1]["t_rx_ns"]) == t_b


def test_a_lone_frame_waits_only_the_window():
    sched = BatchScheduler(_answer, window_ns=20_000_000, max_batch=8)
    a, _idle = _Session(sched), _Session(sched)  # the idle vehicle sends nothing
    sched.start()
    try:
        t = sched.clock.now_ns()
        a.ep.on_message(_frame(0, 1), t_rx=t)
        assert a.got.wait(10)
    finally:
        sched.stop()
    e = a.estimates()[0]
    assert e.t_infer_start_target_ns - t >= 20_000_000  # it waited for the idle vehicle's frame, the window long
    assert sched.stats.sizes == {1: 1}


def test_newest_frame_per_vehicle_wins_and_no_vehicle_starves():
    release = threading.Event()
    started = threading.Event()
    seen: list[list[tuple[int, int]]] = []

    def slow(frames):
        seen.append([(f.vehicle_id, f.frame_id) for f in frames])
        started.set()
        assert release.wait(10)
        return _answer(frames)

    sched = BatchScheduler(slow, window_ns=0, max_batch=2)
    s = [_Session(sched) for _ in range(3)]
    sched.start()
    try:
        s[0].ep.on_message(_frame(0, 0), t_rx=sched.clock.now_ns())
        assert started.wait(10)  # the worker is busy with vehicle 0's frame 0
        s[1].ep.on_message(_frame(1, 0), t_rx=1)
        s[0].ep.on_message(_frame(0, 1), t_rx=3)
        s[0].ep.on_message(_frame(0, 2), t_rx=4)  # replaces frame 1
        s[2].ep.on_message(_frame(2, 0), t_rx=2)
        release.set()
        assert s[0].wait_estimates(2) and s[1].wait_estimates(1) and s[2].wait_estimates(1)
    finally:
        sched.stop()
    # Batches of 2, longest waiting first: vehicles 1 (t_rx 1) and 2 (2), then 0's newest.
    assert seen == [[(0, 0)], [(1, 0), (2, 0)], [(0, 2)]]
    assert s[0].ep.stats.frames_skipped == 1 and sched.stats.replaced == 1
    assert [e.frame_id for e in s[0].estimates()] == [0, 2]


def test_an_output_the_wire_cannot_carry_fails_that_frame_not_the_service():
    from hil.adapters.wire.messages import ErrorMsg

    def bad_for_vehicle_1(frames):
        return [Inference(DrivingState.SAFE, Control(0.0, 2.0 if f.vehicle_id == 1 else 0.5, 0.0), ())
                for f in frames]

    sched = BatchScheduler(bad_for_vehicle_1, window_ns=0, max_batch=4)
    a, b = _Session(sched), _Session(sched)
    sched.start()
    try:
        b.ep.on_message(_frame(1, 0), t_rx=sched.clock.now_ns())
        a.ep.on_message(_frame(0, 0), t_rx=sched.clock.now_ns())
        assert a.wait_estimates(1)
        a.ep.on_message(_frame(0, 1), t_rx=sched.clock.now_ns())
        assert a.wait_estimates(2)  # the worker survived vehicle 1's bad output
    finally:
        sched.stop()
    errors = [m for m in b.sent if isinstance(m, ErrorMsg)]
    assert len(errors) == 1 and "throttle" in errors[0].message and b.ep.stats.infer_errors == 1


def test_scheduler_and_vehicle_options_are_checked():
    with pytest.raises(ValueError, match="max batch"):
        BatchScheduler(_answer, max_batch=0)
    with pytest.raises(ValueError, match="window"):
        BatchScheduler(_answer, window_ns=-1)
    assert parse_vehicles("4") == [0, 1, 2, 3] and parse_vehicles("0,2,3") == [0, 2, 3]
    for bad in ("", "x", "0", "1,a"):
        with pytest.raises(ValueError, match="--vehicles"):
            parse_vehicles(bad)


# -- one process, many vehicles, over the local transport ------------------------------------

_ECHO_SHARED = """
import sys
from hil.adapters.batching import serve_batched
from hil.adapters.wire.messages import Control, DrivingState, Inference
def infer_batch(frames):
    return [Inference(DrivingState.SAFE, Control(0.0, float(f.vehicle_id) / 10, 0.0), ()) for f in frames]
serve_batched(infer_batch, target_name="echo-shared", window_ns=50_000_000, max_batch=8)
"""


def test_one_local_process_serves_every_vehicle_on_its_own_socket(tmp_path: Path):
    from hil.adapters.local.shared_link import SharedLocalLink, SharedLocalTarget
    from hil.timing.clock import MonotonicClock

    clock = MonotonicClock()
    host = SharedLocalTarget([sys.executable, "-c", _ECHO_SHARED], log_path=tmp_path / "t.log",
                             env={"HIL_BATCH_LOG": str(tmp_path / "b.csv")})
    links = [SharedLocalLink(host=host, vehicle_id=v, clock=clock) for v in range(3)]
    try:
        for link in links:
            assert link.open(hello_timeout_s=30).target_name == "echo-shared"
        assert {link.pid for link in links} == {host.pid}  # one process
        for fid in range(2):
            for link in links:
                link.send_frame(frame_id=fid, sim_time_ns=0, t0_ns=clock.now_ns(), width=320, height=240,
                                encoding=ImageEncoding.RGB8, camera=CAM, ego_speed_mps=5.0,
                                data=_frame(link.vehicle_id, fid).data)
            for link in links:
                r = link.recv(timeout_s=30)
                while r is not None and not isinstance(r.msg, Estimate):
                    r = link.recv(timeout_s=30)
                assert r is not None and r.msg.frame_id == fid and r.msg.vehicle_id == link.vehicle_id
                assert r.msg.control.throttle == pytest.approx(link.vehicle_id / 10)
        assert all(link.shm_active for link in links)  # each vehicle's frame ring reached the process
    finally:
        for link in links:
            link.close()
        host.close()
    rows = list(csv.DictReader(open(tmp_path / "b.csv")))
    assert sorted((int(r["vehicle_id"]), int(r["frame_id"])) for r in rows) == [(v, f) for v in range(3)
                                                                              for f in range(2)]
    assert max(int(r["batch_size"]) for r in rows) >= 2  # frames sent together were batched
    assert "shared target: batches=" in (tmp_path / "t.log").read_text()


def test_shared_target_config_needs_local_or_zenoh():
    from hil.common.errors import ConfigError
    from hil.harness.config.loading import load_config, parse_config

    with pytest.raises(ConfigError, match="target.shared"):
        parse_config({"target": {"transport": "tcp", "shared": True}})
    root = Path(__file__).resolve().parents[2]
    cfg = load_config(root / "hil_configs" / "shared.yaml")
    assert cfg.target.shared and cfg.scenario.params["n_vehicles"] == 4
    # The distributed placement its comments show.
    remote = load_config(root / "hil_configs" / "shared.yaml", overrides=[
        "target.transport=zenoh", "target.command=[]", "target.args=[]", 'target.zenoh.connect=["tcp/HOST:7447"]'])
    assert remote.target.shared and remote.target.command == []


# -- the done-when run ---------------------------------------------------------------------


@pytest.mark.slow
def test_four_vehicles_one_shared_cnn_target(hil_run):
    res = hil_run("hil_configs/shared.yaml", overrides=[
        "mode=lockstep", "duration_s=1.5", "engine.capture_phase=aligned", "progress=false",
        "target.estimate_timeout_s=10",  # a loaded 2-core machine: a batch of 4 may take a while
        # One render worker on 2 cores renders the 4 cameras ~3 ms apart: in lockstep a
        # wider window costs nothing and lets their frames meet in one batch.
        'target.args=["--device", "auto", "--threads", "1", "--batch-window-ms", "50", "--max-batch", "16"]'])
    s, out = res.summary, Path(res.run_dir)
    assert len(s["vehicles"]) == 4
    for name, v in s["vehicles"].items():
        assert v["frames_sent"] >= 10 and v["estimates_applied"] == v["frames_sent"], name
        assert v["target"]["name"].startswith("cnn@cpu ("), name
        assert v["latency_ms"]["target_queue"]["count"] == v["frames_sent"], name
    assert not list(out.glob("target-ego*.log")) and (out / "target-shared.log").is_file()
    rows = list(csv.DictReader(open(out / "target-shared-batches.csv")))
    by_frame = {(int(r["vehicle_id"]), int(r["frame_id"])): r for r in rows}
    assert len(by_frame) == sum(v["frames_sent"] for v in s["vehicles"].values())
    # Every frame's target stamps in the recording are the ones the target logged with its batch.
    from mcap.reader import make_reader

    checked = 0
    with open(out / "run.mcap", "rb") as f:
        for _, ch, msg in make_reader(f).iter_messages(topics=[f"/ego{i}/pipeline" for i in range(4)]):
            p = json.loads(msg.data)
            r = by_frame[(int(p["vehicle"][3:]), p["frame_id"])]
            assert (p["t_rx_target_ns"], p["t_infer_start_target_ns"], p["t_infer_end_target_ns"]) == (
                int(r["t_rx_ns"]), int(r["t_infer_start_ns"]), int(r["t_infer_end_ns"]))
            checked += 1
    assert checked == len(rows)
    assert max(int(r["batch_size"]) for r in rows) >= 2  # aligned cameras: frames of several vehicles batched
    for r in rows:  # each batch's parts, all inside its inference
        parts = [int(r[f"{p}_ns"]) for p in ("decode", "nets", "post")]
        assert min(parts) > 0 and sum(parts) <= int(r["t_infer_end_ns"]) - int(r["t_infer_start_ns"])
    tb = s["target_batches"]  # the summary counts the batches by size
    assert tb["batches"] == len({r["batch"] for r in rows})
    assert sum(int(k) * n for k, n in tb["by_size"].items()) == len(rows)


def _send_and_get(link, clock, fid: int) -> Estimate:
    link.send_frame(frame_id=fid, sim_time_ns=0, t0_ns=clock.now_ns(), width=320, height=240,
                    encoding=ImageEncoding.RGB8, camera=CAM, ego_speed_mps=5.0, data=_frame(link.vehicle_id, fid).data)
    r = link.recv(timeout_s=30)
    while r is not None and not isinstance(r.msg, Estimate):
        r = link.recv(timeout_s=30)
    assert r is not None
    return r.msg


def test_shared_zenoh_target_one_session_each_vehicles_keys(tmp_path: Path):
    """``target.shared`` over Zenoh through the harness's launch path: one process
    (started once), every vehicle's link on the same endpoint under its own keys."""
    import queue

    from hil.harness.config.loading import parse_config
    from hil.harness.run.shared_target import BATCH_LOG_NAME, LOG_NAME
    from hil.harness.run.target_launch import make_link
    from hil.timing.clock import MonotonicClock
    from tests.adapters.zenoh.pair import free_port

    port = free_port()
    script = "from hil.adapters.zenoh.options import ZenohOptions\n" + _ECHO_SHARED.replace(
        'window_ns=50_000_000, max_batch=8)', 'window_ns=50_000_000, max_batch=8, transport="zenoh", '
        f'vehicles=[0, 1], options=ZenohOptions(listen=["tcp/127.0.0.1:{port}"]))')
    cfg = parse_config({"target": {"transport": "zenoh", "shared": True, "command": ["{python}", "-c", script],
                                   "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]}}})
    clock = MonotonicClock()
    link0, proc = make_link(cfg, vehicle_id=0, vehicle="ego0", clock=clock, out_dir=tmp_path, rx=queue.Queue())
    link1, proc1 = make_link(cfg, vehicle_id=1, vehicle="ego1", clock=clock, out_dir=tmp_path, rx=queue.Queue())
    assert proc is not None and proc1 is None  # started once, by vehicle 0's link
    try:
        for link in (link0, link1):
            assert link.open(hello_timeout_s=30).target_name == "echo-shared"
        for link in (link0, link1):
            est = _send_and_get(link, clock, 3)
            assert (est.vehicle_id, est.frame_id) == (link.vehicle_id, 3)
            assert est.control.throttle == pytest.approx(link.vehicle_id / 10)
    finally:
        link0.close()
        link1.close()
        proc.close()
    rows = list(csv.DictReader(open(tmp_path / BATCH_LOG_NAME)))
    assert sorted(int(r["vehicle_id"]) for r in rows) == [0, 1]
    assert "shared by vehicles 0, 1" in (tmp_path / LOG_NAME).read_text()


@pytest.mark.slow
def test_the_shared_configs_args_also_serve_one_vehicle_per_target(tmp_path: Path):
    """``--set target.shared=false`` on shared.yaml: the same args (``--shared`` too)
    start an ordinary per-vehicle target on the local transport."""
    from hil.adapters.local.link import LocalLink
    from hil.timing.clock import MonotonicClock

    clock = MonotonicClock()
    link = LocalLink(command=[sys.executable, "-m", "hil.targets.cnn", "--shared", "--device", "auto",
                              "--batch-window-ms", "2"], vehicle_id=0, clock=clock, log_path=tmp_path / "t.log")
    try:
        assert link.open(hello_timeout_s=60).target_name.startswith("cnn@")
        est = _send_and_get(link, clock, 5)
        assert (est.vehicle_id, est.frame_id) == (0, 5)
    finally:
        link.close()


def test_link_faults_apply_to_each_vehicle_of_a_shared_target(tmp_path: Path):
    """``target.impair`` with ``target.shared``: each vehicle's link gets its stage."""
    import queue

    from hil.harness.config.loading import parse_config
    from hil.harness.run.target_launch import make_link
    from hil.timing.clock import MonotonicClock

    cfg = parse_config({"target": {"transport": "local", "shared": True, "command": ["{python}", "-c", _ECHO_SHARED],
                                   "impair": {"uplink": {"delay_ms": 40}}}})
    clock = MonotonicClock()
    link, proc = make_link(cfg, vehicle_id=0, vehicle="ego0", clock=clock, out_dir=tmp_path, rx=queue.Queue())
    assert proc is not None
    try:
        assert link.open(hello_timeout_s=30).target_name == "echo-shared"
        t0 = clock.now_ns()
        est = _send_and_get(link, clock, 1)
        assert est.frame_id == 1 and est.t_rx_target_ns - t0 >= 40_000_000  # delayed on the way up
    finally:
        link.close()
        proc.close()
