"""A third Zenoh peer on the run's endpoint (issue 26, item 6): it connects where the
started target listens and subscribes to ``**``. With the default started target the
run's own credentials (``target.zenoh.per_run_auth``) give it no session: it reads
nothing and cannot end the run. Without them (``per_run_auth=false``) it reads the
AI's estimates and its forged BYE to the target ends the run (the target leaves:
"liveliness lost"), and the summary says that the sender cannot be told."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from tests.adapters.zenoh.pair import ROOT, SKIP_REASON, free_port
from tests.conftest import GL_BACKEND

pytestmark = pytest.mark.skipif(SKIP_REASON is not None, reason=SKIP_REASON or "")


class ThirdPeer:
    """A stranger's Zenoh session on ``tcp/127.0.0.1:port``: records every sample it is
    routed and answers the first estimates it reads on a ``.../t2h`` key with a forged BYE to
    each side."""

    def __init__(self, port: int) -> None:
        import zenoh

        from hil.adapters.zenoh.options import ZenohOptions
        from hil.adapters.zenoh.session import make_config

        self.samples: dict[str, int] = {}
        self.forged = threading.Event()
        self.lock = threading.Lock()
        # It retries until the target listens.
        self.session = zenoh.open(make_config(ZenohOptions(connect=[f"tcp/127.0.0.1:{port}"])))
        self.peers_seen = 0
        self.sub = self.session.declare_subscriber("**", self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        from hil.adapters.wire import protocol
        from hil.adapters.wire.messages import Bye

        key = str(sample.key_expr)
        with self.lock:
            self.samples[key] = self.samples.get(key, 0) + 1
            n = self.samples[key]
        if key.endswith("/t2h") and n == 20 and not self.forged.is_set():
            self.forged.set()  # a BYE each way: to the target (h2t) and to the harness (t2h)
            for k in (key.removesuffix("/t2h") + "/h2t", key):
                self.session.put(k, protocol.encode(Bye(0, "forged by a third peer")))

    def close(self) -> None:
        self.peers_seen = len(list(self.session.info.peers_zid()))
        self.sub.undeclare()
        self.session.close()


def _run_with_a_third_peer(out: Path, *extra: str) -> tuple[subprocess.CompletedProcess[str], ThirdPeer]:
    port = free_port()
    peer = ThirdPeer(port)
    try:
        p = subprocess.run([sys.executable, "-m", "hil.harness.cli.main", "run", "hil_configs/remote.yaml",
                            "--out", str(out), "--no-progress", "--set", "duration_s=4",
                            "--set", f"target.zenoh.base_port={port}", "--set", "corner_cases.enabled=false", *extra],
                           cwd=ROOT, env=dict(os.environ, MUJOCO_GL=GL_BACKEND), capture_output=True, text=True,
                           timeout=180, check=False)
    finally:
        peer.close()
    return p, peer


@pytest.mark.slow
def test_a_third_peer_gets_nothing_from_a_started_target(tmp_path: Path) -> None:
    p, peer = _run_with_a_third_peer(tmp_path / "r")
    assert p.returncode == 0, p.stderr[-2000:]
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["ended_by"] == "duration"
    assert summary["vehicles"]["ego0"]["estimates_applied"] > 20
    assert peer.samples == {} and not peer.forged.is_set() and peer.peers_seen == 0
    # the run's credentials reach only the target: nothing of them in the run folder
    log = (tmp_path / "r" / "target-ego0.log").read_text()
    assert "access: user/password of this run" in log
    for f in (tmp_path / "r").rglob("*"):
        if f.is_file() and f.suffix in (".json", ".log", ".html"):
            assert "HIL_ZENOH_AUTH" not in f.read_text(errors="replace")


@pytest.mark.slow
def test_without_run_credentials_a_third_peer_reads_and_ends_the_run(tmp_path: Path) -> None:
    # What the default closes: the same stranger reads the AI's estimates and forges a
    # BYE that ends the run; the summary says the sender cannot be told.
    p, peer = _run_with_a_third_peer(tmp_path / "r", "--set", "target.zenoh.per_run_auth=false")
    assert peer.forged.is_set() and any(k.endswith("/t2h") for k in peer.samples), peer.samples
    assert p.returncode == 1, p.stderr[-2000:]
    ended_by = json.loads((tmp_path / "r" / "summary.json").read_text())["ended_by"]
    assert "its sender cannot be told" in ended_by, ended_by
