"""Zenoh access control (issue 14, item 3): a target started with
``--auth-dictionary`` admits only a harness with its user and password; a peer
without them gets no session at all (so it can neither read frames nor send BYE),
and a refused session is reported as refused, not as "is the target running?"."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hil.common.errors import ConfigError, TargetError
from tests.adapters.zenoh.pair import ROOT, SKIP_REASON, end_process, free_port, zenoh_link

pytestmark = pytest.mark.skipif(SKIP_REASON is not None, reason=SKIP_REASON or "")


def _link(port: int, **options: object):
    return zenoh_link(port, **options)


@pytest.mark.slow
def test_only_a_harness_with_the_password_gets_a_session(tmp_path: Path):
    users = tmp_path / "users.txt"
    users.write_text("hil:s3cret\n")
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "zenoh", "--listen",
                             f"tcp/127.0.0.1:{port}", "--auth-dictionary", str(users), "--keep-serving"],
                            cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    try:
        with _link(port, usrpwd={"user": "hil", "password": "s3cret"}) as link:
            assert link.open(hello_timeout_s=20).target_name == "echo"
        with _link(port) as stranger, pytest.raises(TargetError) as no_pw:
            stranger.open(hello_timeout_s=2.0)
        assert "answers, but no zenoh session came up" in str(no_pw.value), no_pw.value
        with _link(port, usrpwd={"user": "hil", "password": "wrong"}) as wrong, pytest.raises(TargetError) as bad:
            wrong.open(hello_timeout_s=2.0)
        assert "user/password authentication was refused" in str(bad.value), bad.value
    finally:
        proc.terminate()
        end_process(proc)  # type: ignore[arg-type]
        assert proc.stderr is not None
        first = proc.stderr.readline()
        proc.stderr.close()
    assert "access: user/password" in first, first


def test_nothing_listening_is_not_a_refusal():
    with _link(free_port()) as link, pytest.raises(TargetError, match="is the target running"):
        link.open(hello_timeout_s=0.5)


def test_auth_config_takes_the_password_from_the_environment(monkeypatch):
    from hil.harness.config.loading import parse_config

    cfg = parse_config({"target": {"transport": "zenoh", "command": [], "zenoh": {"auth": {"user": "hil"}}}})
    monkeypatch.delenv("HIL_ZENOH_PASSWORD", raising=False)
    with pytest.raises(ConfigError, match="environment variable HIL_ZENOH_PASSWORD"):
        cfg.target.zenoh.auth.usrpwd()
    monkeypatch.setenv("HIL_ZENOH_PASSWORD", "s3cret")
    assert cfg.target.zenoh.auth.usrpwd() == {"user": "hil", "password": "s3cret"}
    assert "s3cret" not in str(cfg.model_dump())
    with pytest.raises(ConfigError, match="target.zenoh.auth"):
        parse_config({"target": {"transport": "can", "command": [], "zenoh": {"auth": {"user": "hil"}}}})


def test_target_cli_tls_options_are_checked(tmp_path: Path):
    p = subprocess.run([sys.executable, "-m", "hil.targets.echo", "--transport", "zenoh", "--listen",
                        f"tcp/127.0.0.1:{free_port()}", "--tls", "root_ca=ca.pem"], cwd=ROOT, capture_output=True,
                       text=True, timeout=60, check=False)
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert "--tls 'root_ca=ca.pem': expected a known TLS key" in p.stderr
