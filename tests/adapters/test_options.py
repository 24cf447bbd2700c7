"""Every transport's options model (hil.adapters.<transport>.options): the one home of
its defaults, which the SDK's command line reads too; a run's own secrets made by the
transport (``for_run``) and told to a target the harness starts (``child_env``), never
shown in a repr."""

from __future__ import annotations

import argparse
import dataclasses
import json

import pytest

from hil.adapters import transports
from hil.adapters.can.options import CanOptions
from hil.adapters.local.options import LocalOptions
from hil.adapters.mixed.options import MixedOptions
from hil.adapters.ros2.options import MAX_DOMAIN_ID, PER_RUN_DOMAINS, Ros2Options, Topics
from hil.adapters.sdk import add_transport_args, transport_options
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.transports import Transport
from hil.adapters.wire.auth import ENV_TOKEN
from hil.adapters.zenoh.options import AUTH_ENV, PREFIX_ENV, ZenohOptions, usrpwd_from_env
from hil.common.errors import ConfigError

MODELS = {Transport.LOCAL: LocalOptions, Transport.ZENOH: ZenohOptions, Transport.CAN: CanOptions,
          Transport.MIXED: MixedOptions, Transport.TCP: TcpOptions, Transport.ROS2: Ros2Options}


def test_each_transport_names_a_frozen_options_model_with_a_child_env() -> None:
    assert set(MODELS) == set(Transport)
    for kind, model in MODELS.items():
        assert transports.options_class(kind) is model
        assert dataclasses.is_dataclass(model) and model.__dataclass_params__.frozen  # type: ignore[attr-defined]
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(model(), dataclasses.fields(model)[0].name, None)
        assert isinstance(model().child_env(), dict)


def _cli(transport: str, monkeypatch: pytest.MonkeyPatch, *extra: str) -> dict[str, object]:
    for name in (PREFIX_ENV, AUTH_ENV):
        monkeypatch.delenv(name, raising=False)
    p = argparse.ArgumentParser()
    add_transport_args(p)  # its defaults are read now: after the environment is set
    return transport_options(p.parse_args(["--transport", transport, *extra]))


def test_the_target_command_line_defaults_are_the_models(monkeypatch: pytest.MonkeyPatch) -> None:
    assert _cli("local", monkeypatch) == {}
    assert _cli("zenoh", monkeypatch)["options"] == ZenohOptions()
    assert _cli("can", monkeypatch)["options"] == CanOptions()
    assert _cli("mixed", monkeypatch)["options"] == MixedOptions()
    assert _cli("tcp", monkeypatch) == {"options": TcpOptions(), "keep_serving": False}
    zenoh = _cli("zenoh", monkeypatch, "--listen", "tcp/0.0.0.0:7447", "--mode", "client", "--vehicle", "2",
                 "--tls", "enable_mtls=true", "--keep-serving")
    assert zenoh == {"options": ZenohOptions(listen=("tcp/0.0.0.0:7447",), mode="client", tls={"enable_mtls": True}),
                     "vehicle_id": 2, "keep_serving": True}


def test_a_bad_option_on_the_command_line_is_one_line_and_exit_2(monkeypatch: pytest.MonkeyPatch,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        _cli("mixed", monkeypatch, "--listen", "tcp/0.0.0.0:7447", "--tls", "root_ca=ca.pem")
    err = capsys.readouterr().err
    assert stop.value.code == 2 and len(err.splitlines()) == 1 and "--tls 'root_ca=ca.pem'" in err


def test_zenoh_for_run_gives_the_run_its_own_keys_and_credentials() -> None:
    base = ZenohOptions(connect=("tcp/127.0.0.1:7447",), key_prefix="hil")
    a = base.for_run(session="00ff", vehicle_id=1, credentials=True)
    b = base.for_run(session="00ff", vehicle_id=1, credentials=True)
    assert a.key_prefix == "hil/run-00ff" and a.connect == base.connect
    assert a.usrpwd is not None and a.usrpwd["user"] == "hil-00ff-v1"
    assert a.usrpwd["password"] != b.usrpwd["password"] and "00ff" not in a.usrpwd["password"]  # fresh randomness
    env = a.child_env()
    assert env[PREFIX_ENV] == "hil/run-00ff" and usrpwd_from_env(env) == a.usrpwd  # what the SDK reads back
    kept = ZenohOptions(usrpwd={"user": "u", "password": "p"}).for_run(session="1", vehicle_id=0, credentials=False)
    assert kept.usrpwd == {"user": "u", "password": "p"} and AUTH_ENV not in kept.child_env()  # never a configured one
    assert base.child_env() == {PREFIX_ENV: "hil"}
    assert MixedOptions(zenoh=a).child_env() == env


def test_tcp_for_run_makes_a_token_only_for_a_started_target(monkeypatch: pytest.MonkeyPatch) -> None:
    started = TcpOptions().for_run(started=True)
    assert started.token and len(started.token) == 64 and started.token != TcpOptions().for_run(started=True).token
    assert started.child_env() == {ENV_TOKEN: started.token}
    assert TcpOptions().for_run(started=False).token is None and TcpOptions().child_env() == {}
    monkeypatch.setenv("HIL_TEST_SHARED", "a-long-enough-shared-token")
    assert TcpOptions().for_run(started=False, token_env="HIL_TEST_SHARED").token == "a-long-enough-shared-token"
    monkeypatch.setenv("HIL_TEST_SHARED", "short")
    with pytest.raises(ConfigError, match="field.x: the token in HIL_TEST_SHARED is 5 bytes"):
        TcpOptions().for_run(started=True, token_env="HIL_TEST_SHARED", field="field.x")


def test_ros2_for_run_gives_the_node_a_domain_of_the_run_and_tells_it_the_topics() -> None:
    o = Ros2Options(compressed=False, topics=Topics(image="/cam3/image", detections=""))
    domains = {o.for_run(session=f"{s:04x}", vehicle_id=v).domain_id for s in range(40) for v in range(3)}
    assert domains <= set(range(PER_RUN_DOMAINS[0], MAX_DOMAIN_ID + 1)) and len(domains) > 10
    run = o.for_run(session="00ff", vehicle_id=2)
    env = run.child_env()
    assert env["ROS_DOMAIN_ID"] == str(run.domain_id) and "<AllowMulticast>false" in env["CYCLONEDDS_URI"]
    assert json.loads(env["HIL_ROS2_TOPICS"]) == {"image": "/cam3/image", "camera_info": "/camera/camera_info",
                                                  "speed": "/vehicle/twist", "control": "/control/ackermann_cmd",
                                                  "detections": ""}
    assert json.loads(Ros2Options().child_env()["HIL_ROS2_TOPICS"])["compressed_image"] == \
        "/camera/image_raw/compressed" == Ros2Options().image_topic
    with pytest.raises(ConfigError, match="domain_id=233"):
        Ros2Options(domain_id=233).child_env()


def test_a_secret_is_never_in_a_repr() -> None:
    zenoh = ZenohOptions().for_run(session="ab", vehicle_id=0, credentials=True)
    assert zenoh.usrpwd is not None and zenoh.usrpwd["password"] not in repr(zenoh)
    assert zenoh.usrpwd["password"] not in repr(MixedOptions(zenoh=zenoh))
    tcp = TcpOptions().for_run(started=True)
    assert tcp.token is not None and tcp.token not in repr(tcp)
