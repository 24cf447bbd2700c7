"""Transport options of the ``target:`` section.

Endpoints, commands and arguments may contain ``{vehicle_id}`` (the vehicle's index)
and ``{port}`` (``zenoh.base_port + vehicle_id``), so one config drives one target
per vehicle::

    target:
      transport: zenoh
      command: ["{python}", "-m", "hil.targets.cv_baseline", "--transport", "zenoh",
                "--listen", "tcp/127.0.0.1:{port}", "--vehicle", "{vehicle_id}"]
      zenoh: {connect: ["tcp/127.0.0.1:{port}"]}

Each section's defaults are its transport's options model's (``ZenohOptions``,
``CanOptions``, ``TcpOptions``, ``Ros2Options`` in ``hil.adapters.<transport>.options``:
one home per default); ``hil.harness.run.link_options`` turns a section into that
model for one vehicle of a run.

For ``zenoh``, ``can`` and ``mixed`` the ``command`` is optional: empty means the
target runs elsewhere (a board on the bench); given, the harness also starts it
locally (a loopback test or a simulated device) and ends it after the run.

A ``mixed`` target (a device that answers on CAN and takes its frames over Zenoh)
uses both sections: frames go over ``zenoh`` and everything else, clock sync
included, over ``can`` (whose ``camera_over`` it ignores: it is always ``none``)::

    target:
      transport: mixed
      command: []
      zenoh: {connect: ["tcp/192.168.1.20:7447"]}
      can: {interface: socketcan, channel: can0}
"""

from __future__ import annotations

import os
import sys
from enum import Enum
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, Field

from hil.adapters.can.options import LOCAL_INTERFACES, CanOptions
from hil.adapters.ros2.options import (IMAGE_QOS, MAX_DOMAIN_ID, REPLY_QOS, DriveLimits, QosProfile, Ros2Options,
                                       Topics, topic_problem)
from hil.adapters.tcp.options import DEFAULT_PORT, TcpOptions
from hil.adapters.zenoh.options import ZenohOptions, endpoint_problem, tls_key_problem
from hil.common.errors import ConfigError
from hil.harness.config.types import MODEL_CONFIG, Float, Int


def _endpoint(value: str) -> str:
    problem = endpoint_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


def _tls_key(value: str) -> str:
    problem = tls_key_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


def _ros_topic(value: str) -> str:
    if value and (problem := topic_problem(value)) is not None:
        raise ValueError(problem)
    return value


# Checked here, so that an endpoint Zenoh can never open (``zzz``, a missing port) or
# an unknown TLS key is refused before the simulator or any target starts.
ZenohEndpoint = Annotated[str, AfterValidator(_endpoint)]
TlsKey = Annotated[str, AfterValidator(_tls_key)]
RosTopic = Annotated[str, AfterValidator(_ros_topic)]  # "" where the topic may be left out


class ZenohMode(str, Enum):
    PEER = "peer"
    CLIENT = "client"


class Congestion(str, Enum):
    BLOCK = "block"
    DROP = "drop"


class ZenohAuthConfig(BaseModel):
    """User/password authentication of the harness's Zenoh session (Zenoh's usrpwd):
    a target started with ``--auth-dictionary FILE`` admits only peers whose
    ``user:password`` is a line of FILE. The password is read from the environment
    variable ``password_env`` when the run starts, so it is never written to a config
    or a run folder."""

    model_config = MODEL_CONFIG

    user: str = Field(min_length=1, max_length=128, pattern=r"^[^:\s]+$")
    password_env: str = Field("HIL_ZENOH_PASSWORD", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")

    def usrpwd(self) -> dict[str, str]:
        """``{"user", "password"}`` for the Zenoh session.

        Raises:
            ConfigError: the environment variable is not set (or empty).
        """
        password = os.environ.get(self.password_env, "")
        if not password:
            raise ConfigError(f"target.zenoh.auth: set the password in the environment variable "
                              f"{self.password_env} (a password is never stored in a config)")
        return {"user": self.user, "password": password}


class ZenohTargetConfig(BaseModel):
    """Zenoh session of the harness. Multicast scouting stays off unless turned on;
    ``tls`` keys pass through to ``transport/link/tls`` (see adapters/zenoh/link.py)."""

    model_config = MODEL_CONFIG

    # A template (not an endpoint): the harness dials vehicle i's target at base_port + i.
    connect: list[ZenohEndpoint] = Field(default_factory=lambda: ["tcp/127.0.0.1:{port}"])
    listen: list[ZenohEndpoint] = Field(default_factory=lambda: list(ZenohOptions.listen))
    mode: ZenohMode = ZenohMode(ZenohOptions.mode)
    key_prefix: str = Field(ZenohOptions.key_prefix, min_length=1)
    base_port: Int = Field(7447, ge=1, le=65535)
    multicast_scouting: bool = ZenohOptions.multicast_scouting
    congestion_control: Congestion = Congestion(ZenohOptions.congestion_control)
    lease_ms: Int = Field(ZenohOptions.lease_ms, ge=100, le=60_000)
    tls: dict[TlsKey, str | bool] | None = None
    auth: ZenohAuthConfig | None = None  # zenoh and mixed transports (see ZenohAuthConfig)
    # A target the harness starts serves keys under <key_prefix>/run-<session> (the run's
    # nonce, given to it in HIL_ZENOH_KEY_PREFIX, which the SDK follows), so no other
    # target on the endpoint (a leftover, a foreign one) can answer for it. Off for a
    # started third-party target that keeps the fixed keys of PROTOCOL.md 10.2.
    per_run_keys: bool = True
    # With per_run_keys and no ``auth``, a started target and the harness also share
    # user/password credentials made for this run (passed in HIL_ZENOH_AUTH, which the
    # SDK follows; never written to the run folder): a third peer on the endpoint gets
    # no session, so it can neither read the run nor end it with a forged BYE.
    per_run_auth: bool = True


class CanTargetConfig(BaseModel):
    """CAN bus of the harness (python-can). ``interface``: socketcan, pcan, kvaser,
    vector, slcan, or virtual (in-process, for tests). Bitrates in bit/s.
    ``camera_over`` applies to ``transport: can``; a mixed target always uses ``none``."""

    model_config = MODEL_CONFIG

    interface: Literal[LOCAL_INTERFACES] = CanOptions.interface  # type: ignore[valid-type]  # buses on this machine
    channel: str = CanOptions.channel
    bitrate: Int = Field(CanOptions.bitrate, ge=10_000, le=1_000_000)
    data_bitrate: Int = Field(CanOptions.data_bitrate, ge=100_000, le=12_000_000)
    camera_over: str = Field(CanOptions.camera_over, pattern="^(isotp|none)$")


class TcpMode(str, Enum):
    CONNECT = "connect"  # the target listens; the harness dials it
    LISTEN = "listen"  # the harness listens; the target dials in


class TcpAuth(str, Enum):
    AUTO = "auto"  # a target proves the run's token when there is one (the harness starts it, or token_env)
    NONE = "none"  # no proof asked: any program on the port (or dialling in first) is measured


class TcpTargetConfig(BaseModel):
    """TCP connection of the harness (adapters/tcp/link.py, PROTOCOL.md section 10.5).
    ``address`` is host:port, ``{port}`` being ``base_port + vehicle_id``; loopback
    unless given otherwise. ``kernel_stamps``: stamp receipt with the kernel's receive
    time (SO_TIMESTAMPNS) rather than when the reader thread woke.

    Which target is measured (PROTOCOL.md 4.8): a target the harness starts
    (``target.command``) gets a fresh per-run token in ``HIL_SESSION_TOKEN`` and must
    prove it; a target started by hand must prove the token in the environment
    variable named by ``token_env`` (set on both sides, never in a file), or, without
    one, is accepted on its HELLO (and ``target.expect_name``). ``auth: none`` asks no
    proof even of a started target (a version-1 target that predates AUTH)."""

    model_config = MODEL_CONFIG

    mode: TcpMode = TcpMode.CONNECT
    address: str = Field("127.0.0.1:{port}", pattern=r"^(tcp/)?(\[[0-9A-Fa-f:.]+\]|[^:\s\[\]]+):(\{port\}|[0-9]{1,5})$")
    base_port: Int = Field(DEFAULT_PORT, ge=1, le=65535)
    kernel_stamps: bool = TcpOptions.kernel_stamps
    token_env: str | None = Field(None, pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    auth: TcpAuth = TcpAuth.AUTO


class Ros2Topics(BaseModel):
    """The ROS 2 topics of a ``ros2`` target (fully qualified; ``{vehicle_id}`` is
    filled). ``image``: default ``/camera/image_raw``, or ``/camera/image_raw/compressed``
    for ``camera.encoding: jpeg`` (image_transport's names). ``speed`` and
    ``detections`` may be ``""`` (not published / not read)."""

    model_config = MODEL_CONFIG

    image: RosTopic | None = None
    camera_info: RosTopic = Field(Topics.camera_info, min_length=1)
    speed: RosTopic = Topics.speed
    clock: RosTopic = Field(Topics.clock, min_length=1)
    control: RosTopic = Field(Topics.control, min_length=1)
    detections: RosTopic = Topics.detections


class Ros2Qos(BaseModel):
    """One direction's ROS 2 QoS (README, "ROS 2")."""

    model_config = MODEL_CONFIG

    reliability: Literal["reliable", "best_effort"] = QosProfile.reliability.value
    history: Literal["keep_last", "keep_all"] = QosProfile.history.value
    depth: Int = Field(QosProfile.depth, ge=1, le=10_000)

    @classmethod
    def of(cls, profile: QosProfile) -> Ros2Qos:
        """The config of ``profile`` (a default of ``hil.adapters.ros2.options``)."""
        return cls(reliability=profile.reliability.value, history=profile.history.value,
                   depth=profile.depth)


class Ros2QosConfig(BaseModel):
    """QoS of the frames the harness offers (images, camera info, speed: reliable, so
    both reliable and best-effort subscribers match; a short history, so a slow node
    costs frames, not memory) and of the answers it asks for."""

    model_config = MODEL_CONFIG

    images: Ros2Qos = Field(default_factory=lambda: Ros2Qos.of(IMAGE_QOS))
    answers: Ros2Qos = Field(default_factory=lambda: Ros2Qos.of(REPLY_QOS))


class Ros2TargetConfig(BaseModel):
    """A ROS 2 node as the target (adapters/ros2/link.py; README, "ROS 2").
    Vehicle ``i``'s node is on DDS domain ``domain_id + i``; a node the harness starts
    (``command``) gets a domain of this run's own instead (``per_run_domain``). Cyclone
    DDS uses ``interface`` only, ``multicast`` off and unicast discovery to ``peers``.
    ``clock``: ``sim`` (header stamps are sim time, ``/clock`` published; the node runs
    with use_sim_time) or ``system`` (stamps are t0 on this host's system clock).
    The control mapping: ``max_accel_mps2``/``max_decel_mps2`` scale acceleration to
    throttle/brake, ``speed_gain_per_s`` turns a speed-only command into one, at or
    below ``stop_speed_mps`` (and not accelerating) the state is STOP."""

    model_config = MODEL_CONFIG

    domain_id: Int = Field(Ros2Options.domain_id, ge=0, le=MAX_DOMAIN_ID)
    per_run_domain: bool = True
    interface: str = Field(Ros2Options.interface, min_length=1)
    peers: list[str] = Field(default_factory=lambda: list(Ros2Options.peers))
    multicast: bool = Ros2Options.multicast
    lease_ms: Int = Field(Ros2Options.lease_ms, ge=100, le=600_000)
    clock: Literal["sim", "system"] = Ros2Options.clock
    topics: Ros2Topics = Field(default_factory=Ros2Topics)
    base_frame: str = Field(Ros2Options.base_frame, min_length=1)
    camera_frame: str = Field(Ros2Options.camera_frame, min_length=1)
    optical_frame: str = Field(Ros2Options.optical_frame, min_length=1)
    qos: Ros2QosConfig = Field(default_factory=Ros2QosConfig)
    max_accel_mps2: Float = Field(DriveLimits.max_accel_mps2, gt=0, le=100)
    max_decel_mps2: Float = Field(DriveLimits.max_decel_mps2, gt=0, le=100)
    speed_gain_per_s: Float = Field(DriveLimits.speed_gain_per_s, gt=0, le=100)
    stop_speed_mps: Float = Field(DriveLimits.stop_speed_mps, ge=0, le=10)


class LinkFaults(BaseModel):
    """One direction's faults (adapters/impair.py, netem's model): ``delay_ms ±
    jitter_ms`` (uniform), probabilities ``loss``, ``reorder`` (skip the delay),
    ``duplicate``, a bandwidth cap ``rate_kbps`` (0: none), at most ``queue_limit``
    messages in flight (more are dropped, counted)."""

    model_config = MODEL_CONFIG

    delay_ms: Float = Field(0.0, ge=0, le=60_000)
    jitter_ms: Float = Field(0.0, ge=0, le=60_000)
    loss: Float = Field(0.0, ge=0, le=1)
    reorder: Float = Field(0.0, ge=0, le=1)
    duplicate: Float = Field(0.0, ge=0, le=1)
    rate_kbps: Float = Field(0.0, ge=0, le=100_000_000)
    queue_limit: Int = Field(1000, ge=1, le=1_000_000)


class ImpairConfig(BaseModel):
    """Link faults in real time, on any transport (``target.impair``), e.g.
    ``--set target.impair.uplink.delay_ms=20 --set target.impair.uplink.jitter_ms=2``.
    Every impaired message is recorded on ``/<vehicle>/impairment``. ``seed``: default
    the run's seed. ``sync``: impair clock-sync probes too (an asymmetric delay then
    biases the clock offset by half the asymmetry, as on a real link)."""

    model_config = MODEL_CONFIG

    uplink: LinkFaults = Field(default_factory=LinkFaults)
    downlink: LinkFaults = Field(default_factory=LinkFaults)
    seed: Int | None = Field(None, ge=0, le=2**63 - 1)
    sync: bool = False

    @property
    def active(self) -> bool:
        return any(v != 0 for d in (self.uplink, self.downlink)
                   for k, v in d.model_dump().items() if k != "queue_limit")


def substitute(text: str, *, vehicle_id: int, base_port: int) -> str:
    """Fill ``{python}``, ``{vehicle_id}`` and ``{port}`` in one command word or endpoint."""
    return (text.replace("{python}", sys.executable).replace("{vehicle_id}", str(vehicle_id))
            .replace("{port}", str(base_port + vehicle_id)))
