"""Whole runs over the network transports: Zenoh to a target process on loopback,
CAN to a device on python-can's virtual bus, and a remote host in another network
namespace (where this machine allows it)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from hil.common.errors import ConfigError
from hil.harness.config.loading import load_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.adapters.can.pair import can_target
from tests.conftest import GL_BACKEND, read_mcap

ROOT = Path(__file__).resolve().parents[3]


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _check_run(result, *, frames: int) -> None:
    v = result.summary["vehicles"]["ego0"]
    assert result.summary["ended_by"] == "duration"
    assert v["frames_sent"] == frames
    assert v["estimates_applied"] + v["dropped"] + v["stale"] == frames
    assert v["estimates_applied"] > 0.9 * frames
    recs = sorted(d["frame_id"] for _, d in read_mcap(result.mcap_path)["/ego0/pipeline"])
    assert recs == list(range(frames))


def test_run_over_zenoh_loopback(tmp_path):
    cfg = load_config(ROOT / "hil_configs/remote.yaml", overrides=[
        "duration_s=2", "progress=false", f"target.zenoh.base_port={_free_port()}",
        'target.command=["{python}", "-m", "hil.targets.echo", "--transport", "zenoh", '
        '"--listen", "tcp/127.0.0.1:{port}", "--throttle", "0.1"]'])
    result = execute(cfg, out_dir=prepare_out_dir(tmp_path / "r"), gl_backend=GL_BACKEND,
                     install_signal_handlers=False)
    _check_run(result, frames=40)
    assert result.summary["vehicles"]["ego0"]["clock"]["synced"]


def test_run_over_can_virtual_bus(tmp_path):
    channel = f"hil-run-{uuid.uuid4().hex}"
    cfg = load_config(ROOT / "hil_configs/can.yaml", overrides=[
        "duration_s=2", "progress=false", "target.can.interface=virtual", f"target.can.channel={channel}"])
    notes: list[str] = []
    with can_target(channel, ["--throttle", "0.1"]):
        result = execute(cfg, out_dir=prepare_out_dir(tmp_path / "r"), gl_backend=GL_BACKEND,
                         install_signal_handlers=False, notify=notes.append)
    _check_run(result, frames=20)
    assert notes and "at most" in notes[0] and "fps" in notes[0]


def test_can_bus_too_slow_is_refused_before_the_run(tmp_path):
    cfg = load_config(ROOT / "hil_configs/can.yaml", overrides=[
        "progress=false", "camera.fps=50", "target.can.interface=virtual", "target.can.channel=unused"])
    out = prepare_out_dir(tmp_path / "r")
    with pytest.raises(ConfigError, match=r"camera.fps=50 needs .* lower fps to"):
        execute(cfg, out_dir=out, gl_backend=GL_BACKEND, install_signal_handlers=False)
    assert not (out / "run.mcap").exists()


def _netns_unavailable() -> str | None:
    if os.geteuid() != 0:
        return "needs root for ip netns"
    if shutil.which("ip") is None:
        return "iproute2 (ip) is not installed"
    probe = f"hilprobe{os.getpid()}"
    p = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if p.returncode != 0:
        return f"ip netns is not permitted here: {p.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


@pytest.mark.slow
def test_remote_host_in_another_network_namespace(tmp_path):
    """Harness and target in two network namespaces joined by a veth pair with
    private addresses inside them: a real network hop, nothing leaves the machine."""
    why = _netns_unavailable()
    if why:
        pytest.skip(why)
    tag = f"{os.getpid() % 10000}"
    ns_h, ns_t = f"hilh{tag}", f"hilt{tag}"
    ip_h, ip_t = "10.231.7.1", "10.231.7.2"
    sh = [
        f"ip netns add {ns_h}", f"ip netns add {ns_t}",
        f"ip link add veh{tag} netns {ns_h} type veth peer name vet{tag} netns {ns_t}",
        f"ip -n {ns_h} addr add {ip_h}/30 dev veh{tag}", f"ip -n {ns_t} addr add {ip_t}/30 dev vet{tag}",
        f"ip -n {ns_h} link set veh{tag} up", f"ip -n {ns_t} link set vet{tag} up",
        f"ip -n {ns_h} link set lo up", f"ip -n {ns_t} link set lo up",
    ]
    target = None
    try:
        for cmd in sh:
            subprocess.run(cmd.split(), check=True, capture_output=True)
        log = open(tmp_path / "target.log", "wb")
        target = subprocess.Popen(["ip", "netns", "exec", ns_t, sys.executable, "-m", "hil.harness.cli.main", "target",
                                   "echo", "--transport", "zenoh", "--listen", f"tcp/{ip_t}:7447",
                                   "--throttle", "0.1"], cwd=ROOT, stdout=log, stderr=log)
        out = tmp_path / "run"
        p = subprocess.run(["ip", "netns", "exec", ns_h, sys.executable, "-m", "hil.harness.cli.main", "run",
                            "hil_configs/remote.yaml", "--out", str(out), "--no-progress",
                            "--set", "duration_s=3", "--set", "target.command=[]",
                            "--set", f'target.zenoh.connect=["tcp/{ip_t}:7447"]'],
                           cwd=ROOT, capture_output=True, text=True, timeout=120,
                           env=dict(os.environ, MUJOCO_GL=GL_BACKEND))
        assert p.returncode == 0, (p.stdout, p.stderr, (tmp_path / "target.log").read_text())
        import json

        s = json.loads((out / "summary.json").read_text())["vehicles"]["ego0"]
        assert s["frames_sent"] == 60 and s["estimates_applied"] >= 54
        assert s["clock"]["synced"] and s["splits_ms"]["uplink"]["count"] > 0
    finally:
        if target is not None:
            target.terminate()
            try:
                target.wait(timeout=10)
            except subprocess.TimeoutExpired:
                target.kill()
                target.wait()
        for ns in (ns_h, ns_t):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
