"""A run measures the target it started or was told to reach, never another one:
a target already listening on the port (a leftover, another run's) cannot answer
for the run's own (per-run Zenoh keys), the failure names the port clash from the
started target's log, and ``target.expect_name`` refuses a foreign HELLO."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import GL_BACKEND

ROOT = Path(__file__).resolve().parents[3]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _hil(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, MUJOCO_GL=GL_BACKEND)
    return subprocess.run([sys.executable, "-m", "hil.harness.cli.main", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout, check=False)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.slow
def test_a_leftover_target_on_the_port_is_never_measured(tmp_path):
    port = _free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("HIL_ZENOH_KEY_PREFIX", None)
    leftover = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "zenoh", "--listen",
                                 f"tcp/127.0.0.1:{port}", "--vehicle", "0", "--keep-serving"], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        while not _listening(port):
            assert time.monotonic() < deadline and leftover.poll() is None, "the leftover target did not start"
            time.sleep(0.1)
        p = _hil("run", "hil_configs/remote.yaml", "--no-progress", "--out", str(tmp_path / "run"),
                 "--set", f"target.zenoh.base_port={port}", "--set", "duration_s=2",
                 "--set", "target.startup_timeout_s=60")
        assert p.returncode == 2, (p.returncode, p.stdout[-1500:], p.stderr[-1500:])
        err = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert len(err) == 1 and "Traceback" not in p.stderr, p.stderr
        assert "exited" in err[0] and "in use" in err[0].lower(), err[0]  # the clash, from the target's own log
        # Stopped when the started target died, not at the 60 s hello timeout.
        assert "stopped waiting for the target's hello" in err[0] and "within 60" not in err[0], err[0]
        assert not (tmp_path / "run" / "summary.json").exists()  # nothing measured
    finally:
        os.killpg(leftover.pid, signal.SIGTERM)
        leftover.wait(10)


@pytest.mark.slow
def test_expect_name_refuses_another_target(tmp_path):
    p = _hil("run", "hil_configs/demo.yaml", "--no-progress", "--out", str(tmp_path / "run"),
             "--set", "duration_s=1", "--set", "target.expect_name=cnn@")
    assert p.returncode == 2, (p.returncode, p.stderr[-1500:])
    err = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and "target.expect_name" in err[0] and "cv" in err[0], err


def _no_token_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("HIL_SESSION_TOKEN", "HIL_SESSION")}
    return dict(env, PYTHONUNBUFFERED="1")


@pytest.mark.slow
def test_a_squatter_on_the_tcp_port_is_never_measured(tmp_path):
    """An echo target already listening on the run's TCP port (serving run after run)
    was measured for the whole run (exit 0). Now it cannot prove the run's token: it
    is refused, the run's own target cannot bind and says so, and the run stops with
    one line naming both; nothing is measured."""
    port = _free_port()
    squatter = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "tcp", "--listen",
                                 f"127.0.0.1:{port}", "--keep-serving", "--name", "squatter"], env=_no_token_env(),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        while not _listening(port):
            assert time.monotonic() < deadline and squatter.poll() is None, "the squatter did not start"
            time.sleep(0.1)
        p = _hil("run", "hil_configs/tcp.yaml", "--no-progress", "--out", str(tmp_path / "run"),
                 "--set", f"target.tcp.base_port={port}", "--set", "duration_s=2",
                 "--set", "target.startup_timeout_s=10")
        assert p.returncode == 2, (p.returncode, p.stdout[-1500:], p.stderr[-1500:])
        err = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert len(err) == 1 and "Traceback" not in p.stderr, p.stderr
        assert "'squatter' does not announce CAP_AUTH" in err[0] and "refused" in err[0], err[0]
        assert "exited" in err[0] and "in use" in err[0], err[0]  # the run's own target, from its log
        assert not (tmp_path / "run" / "summary.json").exists()  # nothing measured
    finally:
        os.killpg(squatter.pid, signal.SIGTERM)
        squatter.wait(10)


@pytest.mark.slow
def test_a_rogue_dialling_a_listening_harness_first_is_never_measured(tmp_path):
    """In listen mode a rogue that dials the harness before the run's own target was
    measured (120 estimates applied, exit 0). Now it is refused every time it dials,
    counted and named, and the run measures its own target."""
    port = _free_port()
    rogue = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "tcp", "--connect",
                              f"127.0.0.1:{port}", "--keep-serving", "--name", "rogue"], env=_no_token_env(),
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:  # it dials every 50 ms, long before the harness (MuJoCo, its processes) listens
        p = _hil("run", "hil_configs/tcp.yaml", "--no-progress", "--out", str(tmp_path / "run"),
                 "--set", f"target.tcp.base_port={port}", "--set", "target.tcp.mode=listen", "--set", "duration_s=2",
                 "--set", 'target.command=["{python}","-m","hil.targets.echo","--transport","tcp","--connect",'
                          '"127.0.0.1:{port}","--name","own"]')
        assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
        import json

        v = json.loads((tmp_path / "run" / "summary.json").read_text())["vehicles"]["ego0"]
        assert v["target"]["name"] == "own" and v["estimates_applied"] > 0
        assert v["link"]["connections_refused"] >= 1, v["link"]
        assert any("'rogue' does not announce CAP_AUTH" in r for r in v["link"]["refused"]), v["link"]
        # The terminal says so too, with the summary's count.
        n = v["link"]["connections_refused"]
        warned = [ln for ln in p.stdout.splitlines() if "refused, not the run's target" in ln]
        assert len(warned) == 1 and f"ego0: {n} connection" in warned[0] and "rogue" in warned[0], p.stdout
    finally:
        os.killpg(rogue.pid, signal.SIGTERM)
        rogue.wait(10)


def test_the_tcp_token_of_a_run(monkeypatch):
    """A started target gets a fresh per-run token; a hand-started one proves the token
    in target.tcp.token_env (checked before the run: unset or short is one clear line,
    never the value); auth: none asks none."""
    from hil.common.errors import ConfigError
    from hil.harness.config.loading import load_config
    from hil.harness.run.link_options import tcp_options

    def tcp_token(cfg):
        return tcp_options(cfg, vehicle_id=0).token

    cfg = ROOT / "hil_configs" / "tcp.yaml"
    a, b = tcp_token(load_config(cfg)), tcp_token(load_config(cfg))
    assert a and b and a != b and len(a) == 64  # per run, 32 random bytes
    assert tcp_token(load_config(cfg, overrides=["target.command=[]"])) is None  # v1 peers started by hand
    assert tcp_token(load_config(cfg, overrides=["target.tcp.auth=none"])) is None
    hand = load_config(cfg, overrides=["target.command=[]", "target.tcp.token_env=HIL_TEST_TCP_TOKEN"])
    monkeypatch.delenv("HIL_TEST_TCP_TOKEN", raising=False)
    with pytest.raises(ConfigError, match=r"target.tcp.token_env: the environment variable HIL_TEST_TCP_TOKEN is not "
                                          r"set"):
        tcp_token(hand)
    monkeypatch.setenv("HIL_TEST_TCP_TOKEN", "short")
    with pytest.raises(ConfigError, match=r"is 5 bytes; use at least 16") as err:
        tcp_token(hand)
    assert "short" not in str(err.value)
    monkeypatch.setenv("HIL_TEST_TCP_TOKEN", "a-long-enough-shared-token")
    assert tcp_token(hand) == "a-long-enough-shared-token"
