"""Zenoh-specific tests (the shared ones are in test_conformance.py). Everything runs on
127.0.0.1 with multicast scouting off; every session and process started is ended."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

zenoh = pytest.importorskip("zenoh")

from hil.adapters.link import open_link  # noqa: E402
from hil.adapters.sdk import Endpoint  # noqa: E402
from hil.adapters.wire import protocol  # noqa: E402
from hil.adapters.wire.messages import (ClockId, Control, DrivingState, Estimate, Frame, Hello,  # noqa: E402
                                        ImageEncoding, Inference, MsgType)
from hil.adapters.zenoh.link import ZenohLink  # noqa: E402
from hil.adapters.zenoh.options import ZenohOptions  # noqa: E402
from hil.adapters.zenoh.session import Keys, config_entries, make_config  # noqa: E402
from hil.adapters.zenoh.target import serve_endpoint  # noqa: E402
from hil.common.errors import ConfigError, TargetError, TransportError  # noqa: E402
from hil.timing.clock import MonotonicClock  # noqa: E402
from tests.adapters.test_conformance import CAM, next_estimate, send_frame  # noqa: E402
from tests.adapters.zenoh.pair import echo_target, free_port  # noqa: E402


def cfg_json(cfg: zenoh.Config, key: str) -> object:
    return json.loads(cfg.get_json(key))


def link_to(*ports: int, vehicle_id: int = 0, **options: Any) -> ZenohLink:
    """A Zenoh link connecting to ``ports`` of 127.0.0.1; ``options``: ``ZenohOptions``'."""
    return ZenohLink(vehicle_id=vehicle_id, clock=MonotonicClock(),
                     options=ZenohOptions(connect=[f"tcp/127.0.0.1:{p}" for p in ports], **options))


@contextlib.contextmanager
def raw_session(**options: Any) -> Iterator[zenoh.Session]:
    s = zenoh.open(make_config(ZenohOptions(**options)))
    try:
        yield s
    finally:
        s.close()


@contextlib.contextmanager
def inproc_target(infer: Callable[[Frame], Inference], port: int, *, name: str = "inproc",
                  scheme: str = "tcp", vehicle_id: int = 0, **options: Any) -> Iterator[Endpoint]:
    """``serve_endpoint`` listening on 127.0.0.1:``port`` (``port`` 0: ``options``, a
    ``ZenohOptions``', say where), on a thread of this process (so no signal handlers)."""
    ep = Endpoint(infer, target_name=name)
    errors: list[BaseException] = []
    if port:
        options["listen"] = [f"{scheme}/127.0.0.1:{port}"]

    def run() -> None:
        try:
            serve_endpoint(ep, options=ZenohOptions(**options), vehicle_id=vehicle_id)
        except BaseException as err:  # reported by the test below
            errors.append(err)

    t = threading.Thread(target=run, name="zenoh-target", daemon=True)
    t.start()
    try:
        yield ep
    finally:
        ep.stop()
        t.join(timeout=10)
        assert not t.is_alive(), "serve_endpoint did not return"
        assert not errors, errors


def safe(frame: Frame) -> Inference:
    del frame
    return Inference(DrivingState.SAFE, Control())


def wait_for(cond: Callable[[], bool], timeout_s: float) -> float:
    """Seconds until ``cond()`` held; fails after ``timeout_s``."""
    t0 = time.monotonic()
    while not cond():
        assert time.monotonic() - t0 < timeout_s, "condition not met in time"
        time.sleep(0.005)
    return time.monotonic() - t0


# -- configuration --------------------------------------------------------------


def test_config_has_no_scouting_and_only_the_explicit_endpoints():
    cfg = make_config(ZenohOptions(mode="peer", connect=["tcp/127.0.0.1:7447"]))
    assert cfg_json(cfg, "mode") == "peer"
    assert cfg_json(cfg, "scouting/multicast/enabled") is False
    assert cfg_json(cfg, "scouting/gossip/enabled") is False
    assert cfg_json(cfg, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert cfg_json(cfg, "listen/endpoints") == []  # not zenoh's default tcp/[::]:0
    assert cfg_json(cfg, "transport/link/tx/lease") == 1000
    link = link_to(7447, listen=["tcp/127.0.0.1:0"])
    assert cfg_json(link.config, "listen/endpoints") == ["tcp/127.0.0.1:0"]
    assert cfg_json(link.config, "scouting/multicast/enabled") is False
    link.close()  # never opened: close is still safe


def test_tls_options_pass_through_and_unknown_keys_are_refused():
    tls = {"root_ca_certificate": "/etc/hil/ca.pem", "enable_mtls": True,
           "connect_certificate": "/etc/hil/h.pem", "connect_private_key": "/etc/hil/h.key"}
    cfg = make_config(ZenohOptions(connect=["tls/device.local:7447"], tls=tls))
    for key, value in tls.items():
        assert cfg_json(cfg, f"transport/link/tls/{key}") == value
    with pytest.raises(ConfigError, match="root_ca_certificate"):
        config_entries(ZenohOptions(tls={"root_ca": "ca.pem"}))


@pytest.mark.parametrize("options, match", [
    ({"mode": "router"}, "mode"),
    ({"connect": ["127.0.0.1:7447"]}, "PROTOCOL/ADDRESS"),
    ({"connect": "tcp/127.0.0.1:7447"}, "list of endpoints"),
    ({"key_prefix": "hil/**"}, "key_prefix"),
    ({"key_prefix": "/hil"}, "key_prefix"),
    ({"congestion_control": "lossy"}, "congestion_control"),
    ({"lease_ms": 10}, "lease_ms"),
    ({"connect": [], "listen": []}, "at least one"),
])
def test_bad_options_are_refused_before_anything_opens(options, match):
    bad = ZenohOptions(**{"connect": ["tcp/127.0.0.1:7447"], **options})
    with pytest.raises(ConfigError, match=match):
        ZenohLink(vehicle_id=0, clock=MonotonicClock(), options=bad)


def test_keys_are_per_prefix_and_vehicle():
    k = Keys.of("hil/run-a", 3)
    assert (k.h2t, k.t2h, k.alive, k.harness) == (
        "hil/run-a/v3/h2t", "hil/run-a/v3/t2h", "hil/run-a/v3/alive", "hil/run-a/v3/harness")
    assert Keys.of("hil/run-b", 3).h2t != k.h2t


def test_target_needs_an_endpoint():
    with pytest.raises(ConfigError, match="--listen"):
        serve_endpoint(Endpoint(safe, target_name="x"))


# -- traffic -----------------------------------------------------------------------


def test_open_link_by_name_and_raw_320x240_frame_round_trip():
    seen: list[bytes] = []

    def infer(frame: Frame) -> Inference:
        seen.append(frame.data)
        return Inference(DrivingState.SLOW, Control(throttle=0.5))

    data = os.urandom(320 * 240 * 3)  # 230 400 bytes
    port = free_port()
    with inproc_target(infer, port):
        with open_link("zenoh", vehicle_id=0, clock=MonotonicClock(),
                       options=ZenohOptions(connect=[f"tcp/127.0.0.1:{port}"])) as link:
            link.open(hello_timeout_s=10)
            for i in range(3):
                link.send_frame(frame_id=i, sim_time_ns=0, t0_ns=link.clock.now_ns(), width=320, height=240,
                                encoding=ImageEncoding.RGB8, camera=CAM, ego_speed_mps=0.0, data=data)
                est, _ = next_estimate(link)
                assert (est.frame_id, est.state, est.control.throttle) == (i, DrivingState.SLOW, 0.5)
            assert seen == [data] * 3
            assert link.stats.bytes_sent > 3 * len(data)
            assert link.zenoh_stats.put_failures == 0


def test_two_vehicles_on_one_host_do_not_cross_talk(tmp_path: Path):
    p1, p2 = free_port(), free_port()
    with echo_target(tmp_path / "v1.log", p1, ["--vehicle", "1", "--name", "one", "--throttle", "0.1"]), \
         echo_target(tmp_path / "v2.log", p2, ["--vehicle", "2", "--name", "two", "--throttle", "0.2"]):
        # Both links reach both targets: only the keys keep them apart.
        with link_to(p1, p2, vehicle_id=1) as l1, link_to(p1, p2, vehicle_id=2) as l2:
            assert l1.open(hello_timeout_s=20).target_name == "one"
            assert l2.open(hello_timeout_s=20).target_name == "two"
            for i in range(10):
                send_frame(l1, i)
                send_frame(l2, 100 + i)
                e1, _ = next_estimate(l1)
                e2, _ = next_estimate(l2)
                assert (e1.vehicle_id, e1.frame_id, round(e1.control.throttle, 3)) == (1, i, 0.1)
                assert (e2.vehicle_id, e2.frame_id, round(e2.control.throttle, 3)) == (2, 100 + i, 0.2)
            time.sleep(0.1)  # anything stray would have arrived by now
            for link in (l1, l2):
                left = [r.msg for r in iter(lambda lk=link: lk.recv(timeout_s=0), None)]
                assert not [m for m in left if isinstance(m, (Estimate, Hello))], left


@pytest.mark.parametrize("choice, expected", [("block", "BLOCK"), ("drop", "DROP")])
def test_congestion_control_choice_reaches_the_wire(choice, expected):
    got: list[zenoh.CongestionControl] = []
    port, spy_port = free_port(), free_port()
    with inproc_target(safe, port), raw_session(listen=[f"tcp/127.0.0.1:{spy_port}"]) as spy:
        sub = spy.declare_subscriber(Keys.of("hil", 0).h2t, lambda s: got.append(s.congestion_control))
        with link_to(port, spy_port, congestion_control=choice) as link:
            link.open(hello_timeout_s=10)
            assert link.zenoh._publisher.congestion_control == getattr(zenoh.CongestionControl, expected)
            deadline = time.monotonic() + 5  # until the spy's subscription has reached the link
            for i in range(1000):
                send_frame(link, i)
                next_estimate(link)
                if got or time.monotonic() > deadline:
                    break
        sub.undeclare()
    assert got, "the spy saw no frame"
    assert all(c == getattr(zenoh.CongestionControl, expected) for c in got), got


def make_certs(d: Path, name: str) -> tuple[Path, Path, Path]:
    """A throwaway CA and a server certificate for 127.0.0.1: (ca.pem, cert.pem, key.pem)."""
    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True, timeout=30)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    ssl("req", "-x509", *ec, "-keyout", f"{name}-ca.key", "-out", f"{name}-ca.pem", "-days", "1",
        "-subj", f"/CN={name}-ca")
    ssl("req", *ec, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", "/CN=localhost")
    (d / "ext.cnf").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n"
                               "extendedKeyUsage=serverAuth\n")
    ssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{name}-ca.pem", "-CAkey", f"{name}-ca.key",
        "-CAcreateserial", "-out", f"{name}.pem", "-days", "1", "-extfile", "ext.cnf")
    return d / f"{name}-ca.pem", d / f"{name}.pem", d / f"{name}.key"


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make certificates")
def test_tls_link_trusts_only_its_ca(tmp_path: Path):
    ca, cert, key = make_certs(tmp_path, "dev")
    other_ca, _, _ = make_certs(tmp_path, "other")
    port = free_port()
    tls_target = {"listen_certificate": str(cert), "listen_private_key": str(key)}
    with inproc_target(safe, port, scheme="tls", tls=tls_target, name="tls-echo"):
        with _tls_link(port, other_ca) as stranger, pytest.raises(TargetError, match="TLS handshake was refused"):
            stranger.open(hello_timeout_s=1.0)  # the handshake fails: said so, not "is the target running?"
        with _tls_link(port, ca) as link:
            assert link.open(hello_timeout_s=10).target_name == "tls-echo"
            send_frame(link, 3)
            assert next_estimate(link)[0].frame_id == 3


def _tls_link(port: int, ca: Path) -> ZenohLink:
    return ZenohLink(vehicle_id=0, clock=MonotonicClock(),
                     options=ZenohOptions(connect=[f"tls/127.0.0.1:{port}"], tls={"root_ca_certificate": str(ca)}))


def test_client_mode_through_a_router():
    port = free_port()
    router_cfg = make_config(ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"]))
    router_cfg.insert_json5("mode", '"router"')
    router = zenoh.open(router_cfg)
    try:
        client: dict[str, Any] = {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]}
        with inproc_target(safe, 0, name="behind-router", vehicle_id=4, **client), \
             ZenohLink(vehicle_id=4, clock=MonotonicClock(), options=ZenohOptions(**client)) as link:
            assert link.open(hello_timeout_s=10).target_name == "behind-router"
            send_frame(link, 9)
            assert next_estimate(link)[0].frame_id == 9
    finally:
        router.close()


def test_client_mode_without_a_router_fails_at_open():
    link = link_to(free_port(), mode="client")
    with link, pytest.raises(TransportError, match="cannot open a zenoh session"):
        link.open(hello_timeout_s=1)


# -- liveness ----------------------------------------------------------------------


def test_killed_target_is_noticed_by_liveliness(tmp_path: Path):
    port = free_port()
    with echo_target(tmp_path / "t.log", port) as proc, link_to(port) as link:
        link.open(hello_timeout_s=20)
        os.kill(proc.pid, signal.SIGKILL)
        took = wait_for(lambda: not link.alive, 1.0)
        assert "liveliness" in (link.peer_gone_reason or "")
        assert took < 0.5


def test_frozen_target_is_noticed_when_its_lease_expires(tmp_path: Path):
    port = free_port()
    with echo_target(tmp_path / "t.log", port) as proc, link_to(port) as link:
        link.open(hello_timeout_s=20)
        os.kill(proc.pid, signal.SIGSTOP)  # the socket stays open; only the lease can tell
        try:
            took = wait_for(lambda: not link.alive, 3.0)
        finally:
            os.kill(proc.pid, signal.SIGKILL)
        assert 0.5 < took < 2.5, took  # lease 1 s (zenoh's default, 10 s, would fail)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_stopped_target_says_bye(tmp_path: Path, sig: signal.Signals):
    port = free_port()
    with echo_target(tmp_path / "t.log", port) as proc, link_to(port) as link:
        link.open(hello_timeout_s=20)
        proc.send_signal(sig)
        wait_for(lambda: not link.alive, 5.0)
        assert "bye" in (link.peer_gone_reason or "")
        link.close()  # the target waits for us to leave (at most BYE_LINGER_S)
        assert proc.wait(timeout=5) == 0


def test_target_stops_when_the_harness_vanishes(tmp_path: Path):
    port = free_port()
    keys = Keys.of("hil", 0)
    with echo_target(tmp_path / "t.log", port) as proc, \
         raw_session(connect=[f"tcp/127.0.0.1:{port}"]) as s:
        up = threading.Event()
        sub = s.liveliness().declare_subscriber(keys.alive, lambda _: up.set(), history=True)
        token = s.liveliness().declare_token(keys.harness)
        assert up.wait(20)
        token.undeclare()  # as if the harness crashed: no BYE
        assert proc.wait(timeout=5) == 0
        sub.undeclare()


@contextlib.contextmanager
def finishing_target(port: int, *, comes_back: bool) -> Iterator[Callable[[], None]]:
    """A target serving run after run, as a bare Zenoh session listening on ``port``,
    caught between two runs: it holds the token of the run it is finishing; the
    function yielded undeclares it once the harness asks for HELLO and, if
    ``comes_back``, then declares the next run's token and answers HEARTBEATs."""
    keys = Keys.of("hil", 0)
    with raw_session(listen=[f"tcp/127.0.0.1:{port}"]) as s:
        asked, next_run = threading.Event(), threading.Event()

        def on_h2t(sample: zenoh.Sample) -> None:
            data = sample.payload.to_bytes()
            if protocol.decode_header(data).type is MsgType.HEARTBEAT:
                asked.set()
                if next_run.is_set():
                    s.put(keys.t2h, protocol.encode(Hello("next-run", protocol.VERSION, ClockId.MONOTONIC, 1)))

        entities: list[Any] = [s.declare_subscriber(keys.h2t, on_h2t), s.liveliness().declare_token(keys.alive)]

        def finish_run() -> None:
            assert asked.wait(20), "the harness never asked for HELLO"
            entities.pop().undeclare()  # the finished run's token: its DELETE reaches the harness
            time.sleep(0.2)
            if comes_back:
                entities.append(s.liveliness().declare_token(keys.alive))
                next_run.set()

        yield finish_run


@pytest.mark.parametrize("comes_back", [True, False])
def test_token_gone_before_hello_is_a_run_ending_not_the_target(comes_back: bool):
    """CI caught ``hil target --transport zenoh`` between two runs: the next harness saw
    the finished run's token go and called the target gone, then got its HELLO."""
    port = free_port()
    with finishing_target(port, comes_back=comes_back) as finish_run, link_to(port) as link:
        opened: list[Any] = []
        opener = threading.Thread(target=lambda: opened.append(_open_or_error(link, 3.0)))
        opener.start()
        finish_run()
        opener.join(10)
        if comes_back:
            assert isinstance(opened[0], Hello) and opened[0].target_name == "next-run", opened
            time.sleep(0.2)
            assert link.alive, link.peer_gone_reason
        else:
            assert isinstance(opened[0], TargetError), opened
            assert "went away before its HELLO" in str(opened[0]), opened[0]


def _open_or_error(link: ZenohLink, timeout_s: float) -> Hello | TargetError:
    try:
        return link.open(hello_timeout_s=timeout_s)
    except TargetError as err:
        return err


# -- diagnostics -------------------------------------------------------------------


def test_no_target_says_what_to_check(tmp_path: Path):
    with link_to(free_port()) as link, pytest.raises(TargetError, match="no zenoh peer reached"):
        link.open(hello_timeout_s=0.5)
    port = free_port()
    with echo_target(tmp_path / "t.log", port, ["--vehicle", "5"]) as proc, link_to(port, vehicle_id=0) as link:
        with pytest.raises(TargetError, match="--vehicle"):
            link.open(hello_timeout_s=1.5)
        proc.terminate()  # it serves vehicle 5: our BYE is not for it
