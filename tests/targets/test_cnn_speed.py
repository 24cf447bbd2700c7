"""The CNN target's speed paths (issue 30): decode workers (threads and processes),
a batch's parts in the batch log, the shared target on workers against the
single-core path (same estimates, exact stamps, no worker left behind on BYE,
SIGTERM or SIGKILL), and the device-selected paths that run on a CPU-only machine
(precision, preprocessing on the device, CUDA code staying off)."""

from __future__ import annotations

import csv
import os
import select
import signal
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from hil.adapters.wire.messages import CameraInfo, Control, DrivingState, Frame, ImageEncoding, Inference  # noqa: E402
from hil.common.errors import ProtocolError  # noqa: E402
from hil.targets.cnn import pool as cnn_pool  # noqa: E402
from hil.targets.cnn.frontend import Frontend  # noqa: E402
from hil.targets.cnn.target import PARTS, CnnTarget, Serving  # noqa: E402


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    """Held-out simulator frames as the wire carries them (JPEG 320x240)."""
    from hil.scenarios.gl import select_backend
    from hil.training import dataset

    select_backend()
    out = []
    for i, s in enumerate(dataset.generate(seed=dataset.HELDOUT_SEED_BASE + 3, n_frames=12)):
        fx, fy, cx, cy, mount, pitch = s.camera
        out.append(Frame(0, i, 0, 0, 0, 320, 240, ImageEncoding.JPEG, CameraInfo(fx, fy, cx, cy, mount, pitch),
                         s.speed_mps, s.jpeg))
    return out


def _raw(frame: Frame) -> Frame:
    """The same frame as RGB8 pixels."""
    from hil.adapters.sdk import decode_image

    rgb = np.ascontiguousarray(decode_image(frame)[:, :, ::-1])
    return Frame(frame.vehicle_id, frame.frame_id, 0, 0, 0, frame.width, frame.height, ImageEncoding.RGB8,
                 frame.camera, frame.ego_speed_mps, rgb.tobytes())


def _exited_within(pids: list[int], timeout_s: float) -> list[int]:
    """The pids (not our children) still running after ``timeout_s``: waits on
    their pidfds, which become readable when the process exits."""
    fds = {}
    for pid in pids:
        try:
            fds[os.pidfd_open(pid)] = pid
        except ProcessLookupError:
            pass  # already gone
    try:
        left = dict(fds)
        while left:
            ready, _, _ = select.select(list(left), [], [], timeout_s)
            if not ready:
                break
            for fd in ready:
                left.pop(fd)
        return sorted(left.values())
    finally:
        for fd in fds:
            os.close(fd)


def _children(pid: int) -> list[int]:
    kids: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        kids += [int(x) for x in (task / "children").read_text().split()]
    return kids


# -- the pools -----------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["thread", "process"])
def test_pools_give_the_nets_the_same_bytes_as_in_process(frames, kind):
    batch = [*frames[:5], _raw(frames[5])]  # JPEG and raw pixels
    inline = Frontend(0, slots=8).prepare(batch, ("det", "steer"))
    with_pool = Frontend(2, kind=kind, slots=8)
    try:
        for names in (("det", "steer"), ("steer",)):
            got = with_pool.prepare(batch, names)
            assert set(got) == set(names)
            for name in names:
                assert got[name].shape == inline[name].shape and np.array_equal(got[name], inline[name]), name
        assert with_pool.describe() == f"2 {kind}{'es' if kind == 'process' else 's'}"
    finally:
        with_pool.close()


def test_a_frame_that_does_not_decode_fails_the_batch_as_in_process(frames):
    bad = Frame(0, 9, 0, 0, 0, 320, 240, ImageEncoding.JPEG, frames[0].camera, 5.0, b"\xff\xd8 not a jpeg")
    short = Frame(0, 9, 0, 0, 0, 320, 240, ImageEncoding.RGB8, frames[0].camera, 5.0, b"\x00" * 10)
    p = cnn_pool.ProcessPool(2, slots=4)
    try:
        for wrong, kind in ((bad, ProtocolError), (short, ValueError)):
            batch = [frames[0], wrong, frames[1]]
            with pytest.raises(kind) as inline:
                Frontend(0, slots=4).prepare(batch, ("det",))
            with pytest.raises(kind) as pooled:
                p.prepare(batch, ("det",))
            assert str(pooled.value) == str(inline.value)
        assert np.array_equal(p.prepare(frames[:2], ("det",))["det"],
                              Frontend(0).prepare(frames[:2], ("det",))["det"])  # and it serves on
    finally:
        p.close()


def test_a_dead_worker_is_reported_once_and_batches_decode_in_process(frames):
    said: list[str] = []
    fe = Frontend(2, slots=4, log=said.append)
    victim, other = fe._pools[cnn_pool.NETS]._workers  # type: ignore[union-attr]
    victim.proc.kill()
    victim.proc.wait(10)
    got = fe.prepare(frames[:4], ("det", "steer"))
    want = Frontend(0).prepare(frames[:4], ("det", "steer"))
    assert all(np.array_equal(got[k], want[k]) for k in want)
    assert len(said) == 1 and "decoding in process" in said[0] and fe.describe() == "in process"
    assert other.proc.poll() is not None and fe.pids == []  # the rest of the pool was ended, not left behind
    fe.prepare(frames[:2], ("det",))
    assert len(said) == 1


# -- the batch log -------------------------------------------------------------------------


def test_the_batch_log_carries_each_batchs_parts(tmp_path: Path):
    from hil.adapters.batching import BatchedEndpoint, BatchLog, BatchScheduler

    parts = iter([(5, 6, 7), RuntimeError("no parts")])

    def last() -> tuple[int, ...]:
        got = next(parts)
        if isinstance(got, Exception):
            raise got
        return got

    def answer(fs):
        return [Inference(DrivingState.SAFE, Control(0.0, 0.0, 0.0), ()) for _ in fs]

    sched = BatchScheduler(answer, window_ns=0, max_batch=4, log=BatchLog(tmp_path / "b.csv", parts=PARTS),
                           batch_parts=last)
    sent: list[bytes] = []
    cv = threading.Condition()

    def send(buf: bytes) -> None:
        with cv:
            sent.append(buf)
            cv.notify_all()

    ep = BatchedEndpoint(sched, target_name="t")
    ep.start(send)
    sched.start()
    try:
        for fid in range(2):
            n = len(sent)
            ep.on_message(Frame(0, fid, 0, 0, 0, 2, 2, ImageEncoding.RGB8, CameraInfo(1, 1, 1, 1, 1), 0.0,
                                b"\0" * 12), t_rx=sched.clock.now_ns())
            with cv:
                assert cv.wait_for(lambda: len(sent) > n, 10)  # this frame's estimate
    finally:
        sched.stop()
    rows = list(csv.DictReader(open(tmp_path / "b.csv")))
    assert list(rows[0])[-3:] == ["decode_ns", "nets_ns", "post_ns"]
    assert [(r["decode_ns"], r["nets_ns"], r["post_ns"]) for r in rows] == [("5", "6", "7"), ("", "", "")]
    with pytest.raises(ValueError, match="plain names"):
        BatchLog(tmp_path / "c.csv", parts=["a,b"])


# -- a shared target on decode workers, real processes --------------------------------------


def _shared(tmp_path: Path, *args: str):
    from hil.adapters.local.shared_link import SharedLocalTarget

    return SharedLocalTarget([sys.executable, "-m", "hil.targets.cnn", "--threads", "1", *args],
                             log_path=tmp_path / "target.log", env={"HIL_BATCH_LOG": str(tmp_path / "b.csv")})


@pytest.mark.slow
def test_shared_target_on_decode_workers_answers_as_the_single_core_path(tmp_path: Path, frames):
    """3 vehicles, 4 rounds of frames on 2 decode worker processes: every estimate is
    the one ``infer_batch`` in this process gives for the same batch, every stamp is
    ordered and the batch log's, each batch's parts lie inside its inference, and
    the workers leave with the target when the harness says BYE."""
    from hil.adapters.local.shared_link import SharedLocalLink
    from hil.adapters.wire import protocol
    from hil.adapters.wire.messages import Estimate
    from hil.timing.clock import MonotonicClock

    clock = MonotonicClock()
    host = _shared(tmp_path, "--decode-workers", "2", "--batch-window-ms", "5000")  # a full batch never waits
    links = [SharedLocalLink(host=host, vehicle_id=v, clock=clock) for v in range(3)]
    got: dict[tuple[int, int], Estimate] = {}
    sent: dict[tuple[int, int], Frame] = {}
    try:
        for link in links:
            link.open(hello_timeout_s=60)
        workers = _children(host.pid)
        assert len(workers) == 2 and all(b"decode_worker" in Path(f"/proc/{p}/cmdline").read_bytes()
                                         for p in workers)
        for rnd in range(4):
            for link in links:
                f = frames[(rnd * 3 + link.vehicle_id) % len(frames)]
                sent[(link.vehicle_id, rnd)] = f
                link.send_frame(frame_id=rnd, sim_time_ns=0, t0_ns=clock.now_ns(), width=320, height=240,
                                encoding=ImageEncoding.JPEG, camera=f.camera, ego_speed_mps=f.ego_speed_mps,
                                data=f.data)
            for link in links:
                r = link.recv(timeout_s=60)
                while r is not None and not isinstance(r.msg, Estimate):
                    r = link.recv(timeout_s=60)
                assert r is not None
                got[(r.msg.vehicle_id, r.msg.frame_id)] = r.msg
    finally:
        for link in links:
            link.close()
        host.close()
    assert _exited_within(workers, 10.0) == []  # BYE: the target left and took its workers
    rows = list(csv.DictReader(open(tmp_path / "b.csv")))
    assert len(rows) == 12 and len({r["batch"] for r in rows}) == 4
    single = CnnTarget()
    torch.set_num_threads(1)
    for batch in sorted({r["batch"] for r in rows}, key=int):
        members = [r for r in rows if r["batch"] == batch]  # in the order the batch held them
        keys = [(int(r["vehicle_id"]), int(r["frame_id"])) for r in members]
        # The frames as the target read them off the wire (float32 camera and speed).
        want = single.infer_batch([protocol.decode(protocol.encode(
            Frame(v, fid, 0, 0, 0, 320, 240, ImageEncoding.JPEG, sent[(v, fid)].camera, sent[(v, fid)].ego_speed_mps,
                  sent[(v, fid)].data))) for v, fid in keys])
        for (v, fid), r, w in zip(keys, members, want):
            e = got[(v, fid)]
            # The wire carries float32: what the single-core path's answer reads after it.
            w = protocol.decode(protocol.encode(Estimate(v, fid, w.state, w.control, tuple(w.objects), 0, 0, 0, 0)))
            assert (e.state, e.control, e.objects) == (w.state, w.control, w.objects), (v, fid)
            assert (e.t_rx_target_ns, e.t_infer_start_target_ns, e.t_infer_end_target_ns) == (
                int(r["t_rx_ns"]), int(r["t_infer_start_ns"]), int(r["t_infer_end_ns"]))
            assert e.t_rx_target_ns <= e.t_infer_start_target_ns < e.t_infer_end_target_ns <= e.t_reply_target_ns
            parts = [int(r[f"{p}_ns"]) for p in PARTS]
            assert all(x > 0 for x in parts)  # decode included: it runs inside the batch's inference
            assert sum(parts) <= e.t_infer_end_target_ns - e.t_infer_start_target_ns
    log = (tmp_path / "target.log").read_text()
    assert "decode 2 processes" in log and "decode=2_processes" in log


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_no_decode_worker_outlives_its_target(tmp_path: Path, sig):
    """SIGTERM: the target leaves through its finally blocks and closes the pool
    (exit 0, its status line written); SIGKILL: the kernel ends the workers
    (PR_SET_PDEATHSIG). Either way none is left."""
    from hil.adapters.local.shared_link import SharedLocalLink
    from hil.timing.clock import MonotonicClock

    host = _shared(tmp_path, "--decode-workers", "2")
    link = SharedLocalLink(host=host, vehicle_id=0, clock=MonotonicClock())
    try:
        link.open(hello_timeout_s=60)
        workers = _children(host.pid)
        assert len(workers) == 2
        os.kill(host.pid, sig)
        assert host.proc is not None
        code = host.proc.wait(30)
        assert _exited_within(workers, 10.0) == []
    finally:
        link.close()
        host.close()
    if sig == signal.SIGTERM:
        log = (tmp_path / "target.log").read_text()
        assert code == 0 and "cnn: SIGTERM: stopping" in log and "decode=2_processes" in log, log[-2000:]


# -- options and device selection ------------------------------------------------------------


@pytest.mark.parametrize("argv,needle", [
    (["--decode-workers", "x"], "--decode-workers 'x'"),
    (["--precision", "fp8"], "--precision 'fp8'"),
    (["--device", "cuda"], "--device 'cuda'"),
])
def test_bad_speed_options_are_one_line_and_exit_2(capsys, argv, needle):
    if argv[0] == "--device" and torch.cuda.is_available():
        pytest.skip("CUDA is here: --device cuda is valid")
    from hil.targets.cnn.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def test_cuda_paths_stay_off_on_the_cpu_and_precision_auto_is_fp32_there():
    from hil.targets.cnn import accel, devprep

    assert accel.parse_precision("auto", torch.device("cpu")) == torch.float32
    assert accel.parse_precision("auto", torch.device("cuda")) == accel.PRECISIONS[accel.CUDA_AUTO]
    assert accel.parse_precision("BF16", torch.device("cpu")) == torch.bfloat16
    assert accel.buckets(16) == [1, 2, 4, 8, 16] and accel.buckets(12) == [1, 2, 4, 8, 12] and accel.buckets(1) == [1]
    assert [accel.bucket_for(n, [1, 2, 4, 8, 12]) for n in (1, 3, 8, 9, 12)] == [1, 4, 8, 12, 12]
    with pytest.raises(ValueError, match="above"):
        accel.bucket_for(13, [1, 2, 4, 8, 12])
    assert devprep.gpu_jpeg_decoder(torch.device("cpu")) is None
    t = CnnTarget(serving=Serving(cuda_graphs=True))
    assert t.nets.graphed == [] and t.speed() == {"decode": "in process", "preprocess": "cpu", "precision": "fp32",
                                                  "cuda_graphs": "none"}
    x = t.nets.to_device("det", np.zeros((2, 120, 160, 3), np.uint8))
    assert x.device.type == "cpu" and tuple(x.shape) == (2, 3, 120, 160) and x.is_contiguous()


def test_decode_workers_auto_measures_and_says_what_it_chose():
    import re

    from hil.targets.cnn.frontend import AUTO_GAIN, auto_frontend, pool_pays

    assert pool_pays(10.0, 10.0 * (1 - AUTO_GAIN)) and not pool_pays(10.0, 10.0 * (1 - AUTO_GAIN) + 0.01)
    said: list[str] = []
    fe = auto_frontend(slots=8, cores=2, log=said.append, reps=3)
    try:
        assert len(said) == 1, said
        t_in, t_pool = (float(x) for x in re.findall(r"([0-9.]+) ms", said[0]))
        chose = said[0].rsplit(": ", 1)[1]
        assert chose == ("2 processes" if pool_pays(t_in, t_pool) else "in process") == fe.describe()
        assert len(fe.pids) == (2 if chose == "2 processes" else 0)  # a pool not taken was ended
    finally:
        fe.close()
    said.clear()
    assert auto_frontend(slots=4, cores=1, log=said.append, reps=1).describe() == "in process"
    assert said[0].endswith("one core: in process")
    one = CnnTarget(serving=Serving(decode_workers=None, batched=False))  # one vehicle: nothing to spread
    assert one.frontend.describe() == "in process"


# -- reduced precision and preprocessing on the device, on the CPU ------------------------------


def test_device_preprocessing_is_opencvs(frames):
    import cv2

    from hil.targets.cnn.devprep import DevicePrep, area_weights, crop_rows, yuv
    from hil.targets.cnn.preprocess import detector_input, steering_input

    for n_in, n_out in ((240, 120), (128, 66), (320, 200), (7, 3)):
        w = area_weights(n_in, n_out)
        assert torch.allclose(w.sum(1), torch.ones(n_out, dtype=torch.float64))
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (2, 3, 9, 11), dtype=np.uint8)
    want = np.stack([cv2.cvtColor(np.ascontiguousarray(i.transpose(1, 2, 0)), cv2.COLOR_BGR2YUV).transpose(2, 0, 1)
                     for i in img])
    assert np.array_equal(yuv(torch.from_numpy(img)).numpy(), want)  # OpenCV's fixed point, exactly
    bgr = np.stack([cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR) for f in frames])
    prep = DevicePrep(torch.device("cpu"))
    full = torch.from_numpy(bgr).permute(0, 3, 1, 2)
    det = prep.detector(full).numpy().transpose(0, 2, 3, 1)
    assert np.array_equal(det, np.stack([detector_input(b) for b in bgr]))  # a 2x shrink: OpenCV's bytes
    steer = prep.steering(full, crop_rows(frames)).numpy().transpose(0, 2, 3, 1)
    ref = np.stack([steering_input(b, f.camera.cy, f.camera.fy, f.camera.pitch_rad) for b, f in zip(bgr, frames)])
    diff = np.abs(steer - ref)
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01  # summed in another order: a level at most, rarely
    rgb = prep.detector(full.flip(1), order="rgb")
    assert torch.equal(rgb, prep.detector(full))


@pytest.mark.parametrize("serving", [Serving(preprocess="device"), Serving(precision="bf16")],
                         ids=["preprocess-device", "bf16"])
def test_the_cpu_runs_the_gpu_paths_and_they_answer_like_fp32(frames, serving):
    """The paths CUDA would take (preprocessing on the device, bf16 nets) run on the
    CPU; on held-out frames they answer as the default path does (same states, the
    steering within 5 mrad). Their accuracy on 500 frames and in closed loop:
    bench/README.md (bench_precision.py)."""
    torch.set_num_threads(1)
    base, fast = CnnTarget(), CnnTarget(serving=serving)
    if serving.precision == "bf16":
        assert {p.dtype for p in fast.nets.det_net.parameters()} == {torch.bfloat16}
    a, b = base.infer_batch(frames), fast.infer_batch(frames)
    assert [x.state for x in a] == [x.state for x in b]
    assert max(abs(x.control.steering_rad - y.control.steering_rad) for x, y in zip(a, b)) < 0.005
    assert sum(len(x.objects) for x in a) == pytest.approx(sum(len(y.objects) for y in b), abs=2)


def test_the_batched_heatmap_decode_is_each_frames_and_max_pools_exactly():
    from torch.nn import functional as F

    from hil.targets.cnn import models

    x = torch.rand(5, 3, 30, 40)
    x[0, 0, 3:6, 3:6] = 0.7  # a plateau: ties
    assert torch.equal(models._max3x3(x), F.max_pool2d(x, 3, 1, 1))
    g = torch.Generator().manual_seed(3)
    maps = torch.randn(6, 7, 30, 40, generator=g) * 3
    batch = models.decode_batch(maps, threshold=0.15)
    assert batch == [models.decode_batch(m[None], threshold=0.15)[0] for m in maps] and any(batch)
    assert models.decode(maps[2], threshold=0.15) == batch[2]
