"""The CNN target as a real program on the local transport: a short run of
``hil_configs/cnn.yaml`` (inference time from the target's own timestamps, in the
summary), and model swaps by a COMMAND over the wire."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hil.adapters.sdk import Endpoint
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import CameraInfo, Command, Estimate, Frame, ImageEncoding
from hil.common.errors import TransportError

CAM = CameraInfo(207.846, 207.846, 160.0, 120.0, 1.3)


def _frame(frame_id: int) -> Frame:
    return Frame(0, frame_id, 0, 0, 0, 320, 240, ImageEncoding.RGB8, CAM, 5.0, bytes(320 * 240 * 3))


def test_sdk_answers_commands_and_announces_them():
    sent: list[bytes] = []
    ep = Endpoint(lambda f: None, target_name="t", on_command=lambda text: f"ok got {text}")  # type: ignore[arg-type]
    ep.start(sent.append)
    try:
        hello = protocol.decode(sent[0])
        assert hello.capabilities & protocol.CAP_COMMANDS
        ep.on_message(Command(0, 5, "swap detector cv", 1), t_rx=2)
        reply = protocol.decode(sent[-1])
        assert isinstance(reply, Command) and reply.seq == 5 and reply.text == "ok got swap detector cv"
    finally:
        ep.join()
    failing = Endpoint(lambda f: None, target_name="t", on_command=lambda text: 1 / 0)  # type: ignore[arg-type]
    plain = Endpoint(lambda f: None, target_name="t")  # type: ignore[arg-type]
    for ep, expect in ((failing, "error: ZeroDivisionError"), (plain, "error: this target accepts no commands")):
        sent.clear()
        ep.start(sent.append)
        try:
            assert bool(protocol.decode(sent[0]).capabilities & protocol.CAP_COMMANDS) == (ep is failing)
            ep.on_message(Command(0, 6, "status", 1), t_rx=2)
            assert protocol.decode(sent[-1]).text.startswith(expect)
        finally:
            ep.join()


def _next(link, kind, timeout_s: float = 30.0):
    r = link.recv(timeout_s=timeout_s)
    while r is not None and not isinstance(r.msg, kind):
        r = link.recv(timeout_s=timeout_s)
    assert r is not None, f"no {kind.__name__} within {timeout_s} s"
    return r.msg


@pytest.mark.slow
def test_models_are_swapped_by_a_command_over_the_transport(tmp_path: Path):
    pytest.importorskip("torch")
    from hil.adapters.link import open_link
    from hil.timing.clock import MonotonicClock

    log = tmp_path / "t.log"
    link = open_link("local", command=[sys.executable, "-m", "hil.targets.cnn", "--name", "cnn-test"],
                     vehicle_id=0, clock=MonotonicClock(), log_path=log)
    try:
        hello = link.open(hello_timeout_s=60)
        assert hello.target_name.startswith("cnn-test@cpu (") and hello.capabilities & protocol.CAP_COMMANDS
        f = _frame(0)
        link.send_frame(frame_id=0, sim_time_ns=0, t0_ns=0, width=f.width, height=f.height, encoding=f.encoding,
                        camera=f.camera, ego_speed_mps=f.ego_speed_mps, data=f.data)
        assert _next(link, Estimate).frame_id == 0
        cmd = link.send_command("swap detector cv")
        reply = _next(link, Command)
        assert reply.seq == cmd.seq and reply.text == "ok detector=cv steering=cnn after_frame=0"
        link.send_command("swap lidar cv")
        assert _next(link, Command).text.startswith("error: unknown slot")
        link.send_frame(frame_id=1, sim_time_ns=0, t0_ns=0, width=f.width, height=f.height, encoding=f.encoding,
                        camera=f.camera, ego_speed_mps=f.ego_speed_mps, data=f.data)
        assert _next(link, Estimate).frame_id == 1
        link.send_command("status")
        status = _next(link, Command).text
        assert "detector=cv" in status and "frames=2" in status and "swaps=1" in status
    finally:
        link.close()
    assert "swap detector cnn -> cv after frame 0" in log.read_text()


def test_a_target_without_commands_is_not_sent_any(tmp_path: Path):
    from hil.adapters.link import open_link
    from hil.timing.clock import MonotonicClock

    link = open_link("local", command=[sys.executable, "-m", "hil.targets.echo"], vehicle_id=0, clock=MonotonicClock(),
                     log_path=tmp_path / "t.log")
    try:
        link.open(hello_timeout_s=30)
        with pytest.raises(TransportError, match="accepts no commands"):
            link.send_command("swap detector cv")
    finally:
        link.close()


@pytest.mark.slow
def test_short_run_reports_inference_time_from_the_targets_stamps(tmp_path: Path):
    pytest.importorskip("torch")
    from hil.harness.config.loading import load_config
    from hil.harness.run.driver import execute, prepare_out_dir
    from tests.conftest import GL_BACKEND

    cfg = load_config("hil_configs/cnn.yaml", overrides=["duration_s=3", "progress=false"])
    result = execute(cfg, out_dir=prepare_out_dir(tmp_path / "cnn"), gl_backend=GL_BACKEND,
                     install_signal_handlers=False)
    s = result.summary
    v = s["vehicles"]["ego0"]
    inference = v["latency_ms"]["inference"]
    print(f"cnn target, 3 s run: inference p50 {inference['p50_ms']:.2f} ms, p99 {inference['p99_ms']:.2f} ms "
          f"over {inference['count']} frames; end to end p50 {v['latency_ms']['end_to_end']['p50_ms']:.2f} ms")
    assert s["ended_by"] == "duration"
    assert v["target"]["name"].startswith("cnn@cpu (")  # the device and its name
    assert inference["count"] >= 0.8 * v["frames_sent"]
    # Not a benchmark (bench/bench_inference.py checks the 15 ms goal): only sane.
    assert 0.0 < inference["p50_ms"] < 100.0


@pytest.mark.slow
def test_served_over_zenoh_like_on_a_remote_host(tmp_path: Path):
    pytest.importorskip("torch")
    from tests.adapters.zenoh.pair import ROOT, SKIP_REASON, end_process, free_port, zenoh_link

    if SKIP_REASON:
        pytest.skip(SKIP_REASON)
    import os
    import subprocess

    port = free_port()
    with open(tmp_path / "t.log", "ab") as log:
        proc = subprocess.Popen([sys.executable, "-m", "hil.harness.cli.main", "target", "cnn", "--transport", "zenoh",
                                 "--listen", f"tcp/127.0.0.1:{port}", "--once"], cwd=ROOT,
                                env=dict(os.environ, PYTHONUNBUFFERED="1"), stdin=subprocess.DEVNULL,
                                stdout=log, stderr=log)
    try:
        with zenoh_link(port) as link:
            hello = link.open(hello_timeout_s=60)
            assert hello.target_name.startswith("cnn@cpu (") and hello.capabilities & protocol.CAP_COMMANDS
            f = _frame(3)
            link.send_frame(frame_id=3, sim_time_ns=0, t0_ns=0, width=f.width, height=f.height, encoding=f.encoding,
                            camera=f.camera, ego_speed_mps=f.ego_speed_mps, data=f.data)
            est = _next(link, Estimate)
            assert est.frame_id == 3 and est.t_infer_end_target_ns > est.t_infer_start_target_ns
            link.send_command("swap steering cv")
            assert _next(link, Command).text == "ok detector=cnn steering=cv after_frame=3"
    finally:
        end_process(proc, grace_s=10.0)
    assert "swap steering cnn -> cv after frame 3" in (tmp_path / "t.log").read_text()


@pytest.mark.slow
def test_a_configured_swap_is_recorded_in_the_run(tmp_path: Path):
    # target.commands sends "swap detector cv" at 1 s of sim time; the command and the
    # target's reply both land in the run's /events.
    pytest.importorskip("torch")
    from hil.harness.config.loading import load_config
    from hil.harness.run.driver import execute, prepare_out_dir
    from tests.conftest import GL_BACKEND, read_mcap

    root = Path(__file__).resolve().parents[2]
    cfg = load_config(root / "hil_configs/cnn.yaml", overrides=[
        "duration_s=2", "progress=false", 'target.commands=[{at_s: 1.0, command: "swap detector cv"}]'])
    result = execute(cfg, out_dir=prepare_out_dir(tmp_path / "r"), gl_backend=GL_BACKEND,
                     install_signal_handlers=False)
    events = [d for _, d in read_mcap(result.mcap_path)["/events"]]
    sent = [e for e in events if e["kind"] == "target_command"]
    replies = [e for e in events if e["kind"] == "target_command_reply"]
    assert [(e["vehicle"], e["text"]) for e in sent] == [("ego0", "swap detector cv")]
    assert sent[0]["sim_time_ns"] == 1_000_000_000
    assert len(replies) == 1 and replies[0]["seq"] == sent[0]["seq"] and replies[0]["text"].startswith("ok")
    assert "detector=cv" in replies[0]["text"]
