"""What a run's config says about one vehicle's link: the target's command line, the
Zenoh key prefix and the TCP token of the run, each transport's link options, and the
link faults to inject. Shared by the per-vehicle launch (``target_launch``) and the shared target."""

from __future__ import annotations

import secrets

from hil.adapters.link import Link
from hil.common.errors import ConfigError
from hil.harness.config.model import RunConfig, Transport
from hil.harness.config.target import TcpAuth, substitute
from hil.timing.clock import Clock


def target_command(cfg: RunConfig, *, vehicle_id: int = 0) -> list[str]:
    """The configured command with ``args`` appended and placeholders filled."""
    port = cfg.target.tcp.base_port if cfg.target.transport == Transport.TCP else cfg.target.zenoh.base_port
    return [substitute(w, vehicle_id=vehicle_id, base_port=port)
            for w in [*cfg.target.command, *cfg.target.args]]


def run_key_prefix(cfg: RunConfig, session: str | None) -> str:
    """The Zenoh key prefix of this run: ``<key_prefix>/run-<session>`` when the harness
    starts the target itself (``target.zenoh.per_run_keys``), else ``key_prefix``."""
    z = cfg.target.zenoh
    if session and cfg.target.command and z.per_run_keys:
        return f"{z.key_prefix}/run-{session}"
    return z.key_prefix


def run_credentials(cfg: RunConfig, session: str | None, vehicle_id: int) -> tuple[str, str] | None:
    """This run's own Zenoh user and password for a target the harness starts
    (``target.zenoh.per_run_auth``), or None. The password is fresh randomness, never
    the session nonce (which summary.json shows)."""
    z = cfg.target.zenoh
    if not (z.per_run_auth and z.auth is None and run_key_prefix(cfg, session) != z.key_prefix):
        return None
    return f"hil-{session}-v{vehicle_id}", secrets.token_urlsafe(24)


def zenoh_options(cfg: RunConfig, vehicle_id: int, session: str | None = None,
                  credentials: tuple[str, str] | None = None) -> dict[str, object]:
    """Keyword options of the Zenoh link of one vehicle (``target.zenoh``);
    ``credentials``: the run's own (``run_credentials``)."""
    from hil.adapters.zenoh.options import run_usrpwd

    z = cfg.target.zenoh
    auth = run_usrpwd(*credentials) if credentials else z.auth.usrpwd() if z.auth else None
    return {"connect": [substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.connect],
            "listen": [substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.listen],
            "mode": z.mode.value, "key_prefix": run_key_prefix(cfg, session), "multicast_scouting": z.multicast_scouting,
            "congestion_control": z.congestion_control.value, "lease_ms": z.lease_ms,
            "tls": dict(z.tls) if z.tls else None, **({"usrpwd": auth} if auth else {})}


def ros2_domain(cfg: RunConfig, vehicle_id: int, session: str | None = None) -> int:
    """The DDS domain of vehicle ``vehicle_id``'s node: this run's own when the harness
    starts the node (``target.ros2.per_run_domain``), else ``domain_id + vehicle_id``.

    Raises:
        ConfigError: the domain is past 232.
    """
    from hil.adapters.ros2.options import check_domain, per_run_domain

    r = cfg.target.ros2
    if session and cfg.target.command and r.per_run_domain:
        return per_run_domain(session, vehicle_id)
    try:
        return check_domain(r.domain_id + vehicle_id)
    except ConfigError as err:
        raise ConfigError(f"target.ros2.domain_id: {r.domain_id} + vehicle {vehicle_id} is past 232 ({err})") from None


def ros2_topics(cfg: RunConfig, vehicle_id: int) -> dict[str, str]:
    """The run's ROS 2 topics by role (``target.ros2.topics``, ``{vehicle_id}`` filled)."""
    t = cfg.target.ros2.topics
    image = t.image or ("/camera/image_raw/compressed" if ros2_compressed(cfg) else "/camera/image_raw")
    out = {"image": image, "camera_info": t.camera_info, "speed": t.speed, "clock": t.clock, "control": t.control,
           "detections": t.detections}
    return {k: substitute(v, vehicle_id=vehicle_id, base_port=0) for k, v in out.items()}


def ros2_compressed(cfg: RunConfig) -> bool:
    """Frames go out as ``CompressedImage`` (JPEG), else as ``Image``."""
    return cfg.camera.encoding.value == "jpeg"


def ros2_options(cfg: RunConfig, vehicle_id: int, session: str | None = None) -> dict[str, object]:
    """Keyword options of the ROS 2 link of one vehicle (``target.ros2``)."""
    import math

    from hil.adapters.ros2.answers import DriveMapping
    from hil.adapters.ros2.options import QosProfile

    r, cam = cfg.target.ros2, cfg.camera
    topics = ros2_topics(cfg, vehicle_id)
    return {"domain_id": ros2_domain(cfg, vehicle_id, session), "interface": r.interface, "peers": tuple(r.peers),
            "multicast": r.multicast, "lease_ms": r.lease_ms, "clock_mode": r.clock,
            "compressed": ros2_compressed(cfg), "image_topic": topics["image"],
            "camera_info_topic": topics["camera_info"], "speed_topic": topics["speed"], "clock_topic": topics["clock"],
            "control_topic": topics["control"], "detections_topic": topics["detections"],
            "base_frame": r.base_frame, "camera_frame": r.camera_frame, "optical_frame": r.optical_frame,
            "mount": (cam.mount_forward_m, cam.mount_lateral_m, cam.mount_height_m, math.radians(cam.pitch_deg),
                      math.radians(cam.yaw_deg)),
            "image_qos": QosProfile(**r.qos.images.model_dump()), "reply_qos": QosProfile(**r.qos.answers.model_dump()),
            "mapping": DriveMapping(max_accel_mps2=r.max_accel_mps2, max_decel_mps2=r.max_decel_mps2,
                                    speed_gain_per_s=r.speed_gain_per_s, stop_speed_mps=r.stop_speed_mps)}


def ros2_node_env(cfg: RunConfig, vehicle_id: int, session: str | None = None) -> dict[str, str]:
    """Environment of a ROS 2 node the harness starts: its domain, Cyclone's loopback
    configuration, and the run's topics for the SDK's ros2 target (``HIL_ROS2_TOPICS``;
    a ROS 2 node is remapped by its own launch arguments instead)."""
    import json

    from hil.adapters.ros2.options import cyclone_xml, node_env

    r = cfg.target.ros2
    topics = ros2_topics(cfg, vehicle_id)
    image_role = "compressed_image" if ros2_compressed(cfg) else "image"
    node = {image_role: topics["image"], **{k: topics[k] for k in ("camera_info", "speed", "control", "detections")}}
    xml = cyclone_xml(interface=r.interface, peers=tuple(r.peers), multicast=r.multicast, lease_ms=r.lease_ms)
    return {**node_env(ros2_domain(cfg, vehicle_id, session), xml), "HIL_ROS2_TOPICS": json.dumps(node)}


def tcp_token(cfg: RunConfig) -> str | None:
    """The token a TCP target must prove (PROTOCOL.md 4.8): the one in
    ``target.tcp.token_env``, else a fresh per-run secret when the harness starts the
    target itself, else None (``target.tcp.auth: none``: always None).

    Raises:
        ConfigError: ``token_env`` names an unset variable, or a token under 16 bytes.
    """
    from hil.adapters.wire.auth import new_token, token_from_env

    tc = cfg.target.tcp
    if tc.auth == TcpAuth.NONE:
        return None
    if tc.token_env:
        raw = token_from_env(tc.token_env, field="target.tcp.token_env", required=True)
        assert raw is not None
        return raw.decode("utf-8")
    return new_token() if cfg.target.command else None


def tcp_options(cfg: RunConfig, vehicle_id: int, token: str | None) -> dict[str, object]:
    """Keyword options of the TCP link of one vehicle (``target.tcp``): ``{mode: address}``
    as ``hil.adapters.tcp.link.TcpLink`` takes it, the token and the expected name."""
    tc = cfg.target.tcp
    return {tc.mode.value: substitute(tc.address, vehicle_id=vehicle_id, base_port=tc.base_port),
            "kernel_stamps": tc.kernel_stamps, "token": token, "expect_name": cfg.target.expect_name}


def can_options(cfg: RunConfig, vehicle_id: int) -> dict[str, object]:
    """Keyword options of the CAN link of one vehicle (``target.can``)."""
    c = cfg.target.can
    return {"interface": c.interface, "channel": substitute(c.channel, vehicle_id=vehicle_id, base_port=0),
            "bitrate": c.bitrate, "data_bitrate": c.data_bitrate}


def impair(cfg: RunConfig, link: Link, *, vehicle_id: int, clock: Clock) -> None:
    """Link faults in real time (``target.impair``, adapters/impair.py), if any."""
    from hil.adapters.impair import stage_for

    stage = stage_for(cfg.target.impair, run_seed=cfg.seed, vehicle_id=vehicle_id, clock=clock)
    if stage is not None:
        link.set_impairment(stage)
