"""A run's link options (harness/run/link_options.py): one function per config section
makes that transport's options model, whose defaults are the section's (one home per
default), and make_link opens every transport with one call, telling a target it
starts what the transport's ``child_env`` says (real child processes)."""

from __future__ import annotations

import dataclasses
import json
import queue
import socket
import sys
from pathlib import Path

import pytest

from hil.adapters import transports
from hil.adapters.can.options import CanOptions
from hil.adapters.ros2.options import DriveLimits, Ros2Options
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.transports import Transport
from hil.adapters.wire.auth import ENV_TOKEN
from hil.adapters.zenoh.options import AUTH_ENV, PREFIX_ENV, ZenohOptions
from hil.harness.config.loading import parse_config
from hil.harness.run.link_options import LINK_OPTIONS, link_options
from hil.timing.clock import MonotonicClock


def _fields(options: object, *names: str) -> dict[str, object]:
    return {n: getattr(options, n) for n in names}


def test_every_transport_has_its_section_s_function_and_it_makes_that_model() -> None:
    assert set(LINK_OPTIONS) == set(Transport)
    for kind in Transport:
        cfg = parse_config({"target": {"transport": kind.value, "command": ["x"]}})
        assert isinstance(link_options(cfg, vehicle_id=0), transports.options_class(kind))


def test_a_section_s_defaults_are_its_model_s() -> None:
    """A default written once: the config's sections take theirs from the models, so
    the options a default config makes are the models' own defaults."""
    cfg = parse_config({"target": {"transport": "zenoh", "command": []}})
    zenoh = LINK_OPTIONS[Transport.ZENOH](cfg, vehicle_id=0)
    same = ("listen", "mode", "key_prefix", "multicast_scouting", "congestion_control", "lease_ms", "tls", "usrpwd")
    assert _fields(zenoh, *same) == _fields(ZenohOptions(), *same)
    assert LINK_OPTIONS[Transport.CAN](cfg, vehicle_id=0) == CanOptions()
    tcp = LINK_OPTIONS[Transport.TCP](cfg, vehicle_id=0)
    same = ("kernel_stamps", "heartbeat_idle_s", "token", "expect_name")
    assert _fields(tcp, *same) == _fields(TcpOptions(), *same) and tcp.connect == "127.0.0.1:7600"
    ros2 = LINK_OPTIONS[Transport.ROS2](cfg, vehicle_id=0)  # camera.encoding: jpeg, the default
    same = ("domain_id", "interface", "peers", "multicast", "lease_ms", "clock", "compressed", "topics",
            "base_frame", "camera_frame", "optical_frame", "image_qos", "reply_qos", "drive")
    assert _fields(ros2, *same) == _fields(Ros2Options(), *same) and ros2.drive == DriveLimits()


def test_a_run_s_own_secrets_only_for_a_target_it_starts() -> None:
    started = parse_config({"target": {"transport": "zenoh", "command": ["x"]}})
    by_hand = parse_config({"target": {"transport": "zenoh", "command": []}})
    own = link_options(started, vehicle_id=1, session="00ff")
    assert isinstance(own, ZenohOptions) and own.key_prefix == "hil/run-00ff" and own.usrpwd is not None
    assert link_options(by_hand, vehicle_id=1, session="00ff") == link_options(by_hand, vehicle_id=1)
    keys_only = parse_config({"target": {"transport": "zenoh", "command": ["x"], "zenoh": {"per_run_auth": False}}})
    assert dataclasses.replace(link_options(keys_only, vehicle_id=1, session="00ff"), key_prefix="hil") == \
        link_options(keys_only, vehicle_id=1)
    ros2 = parse_config({"target": {"transport": "ros2", "command": ["x"], "ros2": {"domain_id": 232}}})
    assert isinstance(r := link_options(ros2, vehicle_id=3, session="00ff"), Ros2Options) and r.domain_id != 235
    from hil.common.errors import ConfigError

    with pytest.raises(ConfigError, match=r"target.ros2.domain_id: 232 \+ vehicle 3 is past 232"):
        link_options(ros2, vehicle_id=3)


# The started target: sends its environment to the test and exits.
TELL = ("import json, os, socket, sys; s = socket.create_connection(('127.0.0.1', int(sys.argv[1]))); "
        "s.sendall(json.dumps(dict(os.environ)).encode()); s.close()")


@pytest.mark.parametrize("transport, told", [
    ("zenoh", {PREFIX_ENV, AUTH_ENV}),
    ("tcp", {ENV_TOKEN}),
    ("ros2", {"ROS_DOMAIN_ID", "CYCLONEDDS_URI", "HIL_ROS2_TOPICS"}),
])
def test_make_link_tells_the_target_it_starts_what_the_transport_says(transport, told, tmp_path: Path) -> None:
    """One call opens any transport: the started target's environment holds the
    options' ``child_env`` (the run's keys, credentials, token or domain) and the session."""
    pytest.importorskip({"zenoh": "zenoh", "ros2": "cyclonedds"}.get(transport, "socket"))
    from hil.harness.run.target_launch import make_link

    with socket.create_server(("127.0.0.1", 0)) as server:
        server.settimeout(30)
        command = [sys.executable, "-c", TELL, str(server.getsockname()[1])]
        cfg = parse_config({"target": {"transport": transport, "command": command}})
        link, proc = make_link(cfg, vehicle_id=0, vehicle="ego0", clock=MonotonicClock(), out_dir=tmp_path,
                               rx=queue.Queue(), session="00ff")
        try:
            assert proc is not None and link.transport_name == transport
            conn, _ = server.accept()  # the target connects once it runs
            with conn:
                env = json.loads(b"".join(iter(lambda: conn.recv(1 << 16), b"")))
            said = link.options.child_env()  # type: ignore[attr-defined]  # every link keeps its model
            assert told <= set(said) and {k: env.get(k) for k in said} == said and env["HIL_SESSION"] == "00ff"
        finally:
            link.close()
            if proc is not None:
                proc.close()
