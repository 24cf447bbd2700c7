"""What a run's config says about one vehicle's link: the target's command line, the
transport's options model built from its ``target.<transport>`` section (one function
per transport, in ``LINK_OPTIONS``; the run's own keys, token, credentials and domain
come from the model's ``for_run``), and the link faults to inject. Shared by the
per-vehicle launch (``target_launch``) and the shared target."""

from __future__ import annotations

import math
from collections.abc import Callable

from hil.adapters.can.options import CanOptions
from hil.adapters.link import Link
from hil.adapters.local.options import LocalOptions
from hil.adapters.mixed.options import MixedOptions
from hil.adapters.ros2.options import DriveLimits, QosProfile, Ros2Options, Topics, check_domain
from hil.adapters.tcp.options import TcpOptions
from hil.adapters.transports import TransportOptions
from hil.adapters.zenoh.options import ZenohOptions
from hil.common.errors import ConfigError
from hil.harness.config.model import RunConfig, Transport
from hil.harness.config.target import TcpAuth, TcpMode, substitute
from hil.timing.clock import Clock


def target_command(cfg: RunConfig, *, vehicle_id: int = 0) -> list[str]:
    """The configured command with ``args`` appended and placeholders filled."""
    port = cfg.target.tcp.base_port if cfg.target.transport == Transport.TCP else cfg.target.zenoh.base_port
    return [substitute(w, vehicle_id=vehicle_id, base_port=port)
            for w in [*cfg.target.command, *cfg.target.args]]


def _started(cfg: RunConfig, session: str | None) -> str | None:
    """The run's session nonce when the harness starts the target itself, else None."""
    return session if session and cfg.target.command else None


def local_options(cfg: RunConfig, *, vehicle_id: int, session: str | None = None) -> LocalOptions:
    """The local link's options: its defaults (no config section; ``target.command`` is the link's own)."""
    return LocalOptions()


def zenoh_options(cfg: RunConfig, *, vehicle_id: int, session: str | None = None) -> ZenohOptions:
    """The Zenoh options of one vehicle (``target.zenoh``): with ``session``, for a
    target the harness starts, keys under ``<key_prefix>/run-<session>``
    (``per_run_keys``) and user/password of the run's own (``per_run_auth``, where
    ``auth`` gives none).

    Raises:
        ConfigError: ``target.zenoh.auth``'s password is not in its environment variable.
    """
    z = cfg.target.zenoh
    options = ZenohOptions(
        connect=tuple(substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.connect),
        listen=tuple(substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.listen),
        mode=z.mode.value, key_prefix=z.key_prefix, multicast_scouting=z.multicast_scouting,
        congestion_control=z.congestion_control.value, lease_ms=z.lease_ms, tls=dict(z.tls) if z.tls else None,
        usrpwd=z.auth.usrpwd() if z.auth else None)
    run = _started(cfg, session)
    if run is not None and z.per_run_keys:  # a third peer gets no session
        options = options.for_run(session=run, vehicle_id=vehicle_id, credentials=z.per_run_auth and z.auth is None)
    return options


def tcp_options(cfg: RunConfig, *, vehicle_id: int, session: str | None = None) -> TcpOptions:
    """The TCP options of one vehicle (``target.tcp``): the address to dial or listen on, receipt
    stamps, the expected name, and the token a target must prove (PROTOCOL.md 4.8):
    the one in ``token_env``, else a fresh per-run secret when the harness starts the
    target itself, else none (``auth: none``: never one).

    Raises:
        ConfigError: ``token_env`` names an unset variable, or a token under 16 bytes.
    """
    tc = cfg.target.tcp
    address = substitute(tc.address, vehicle_id=vehicle_id, base_port=tc.base_port)
    dial = tc.mode == TcpMode.CONNECT
    options = TcpOptions(connect=address if dial else None, listen=None if dial else address,
                         kernel_stamps=tc.kernel_stamps, expect_name=cfg.target.expect_name)
    if tc.auth == TcpAuth.NONE:
        return options
    return options.for_run(started=bool(cfg.target.command), token_env=tc.token_env, field="target.tcp.token_env")


def can_options(cfg: RunConfig, *, vehicle_id: int, session: str | None = None) -> CanOptions:
    """The CAN options of one vehicle (``target.can``)."""
    c = cfg.target.can
    return CanOptions(interface=c.interface, channel=substitute(c.channel, vehicle_id=vehicle_id, base_port=0),
                      bitrate=c.bitrate, data_bitrate=c.data_bitrate, camera_over=c.camera_over)


def mixed_options(cfg: RunConfig, *, vehicle_id: int, session: str | None = None) -> MixedOptions:
    """A mixed target's: frames over ``target.zenoh``, the rest over ``target.can``."""
    return MixedOptions(zenoh=zenoh_options(cfg, vehicle_id=vehicle_id, session=session),
                        can=can_options(cfg, vehicle_id=vehicle_id))


def ros2_options(cfg: RunConfig, *, vehicle_id: int, session: str | None = None) -> Ros2Options:
    """The ROS 2 options of one vehicle (``target.ros2``, and the camera's encoding and
    mount): its node's DDS domain is this run's own when the harness starts the node
    (``per_run_domain``), else ``domain_id + vehicle_id``.

    Raises:
        ConfigError: the domain is past 232.
    """
    r, cam = cfg.target.ros2, cfg.camera
    topics = Topics(**{role: substitute(name or "", vehicle_id=vehicle_id, base_port=0)
                       for role, name in r.topics.model_dump().items()})
    run = _started(cfg, session)
    domain = r.domain_id + vehicle_id
    if run is None or not r.per_run_domain:
        try:
            check_domain(domain)
        except ConfigError as err:
            raise ConfigError(f"target.ros2.domain_id: {r.domain_id} + vehicle {vehicle_id} is past 232 "
                              f"({err})") from None
    options = Ros2Options(
        domain_id=domain, interface=r.interface, peers=tuple(r.peers), multicast=r.multicast, lease_ms=r.lease_ms,
        clock=r.clock, compressed=cam.encoding.value == "jpeg", topics=topics, base_frame=r.base_frame,
        camera_frame=r.camera_frame, optical_frame=r.optical_frame,
        mount=(cam.mount_forward_m, cam.mount_lateral_m, cam.mount_height_m, math.radians(cam.pitch_deg),
               math.radians(cam.yaw_deg)),
        image_qos=QosProfile(**r.qos.images.model_dump()), reply_qos=QosProfile(**r.qos.answers.model_dump()),
        drive=DriveLimits(max_accel_mps2=r.max_accel_mps2, max_decel_mps2=r.max_decel_mps2,
                          speed_gain_per_s=r.speed_gain_per_s, stop_speed_mps=r.stop_speed_mps))
    return options.for_run(session=run, vehicle_id=vehicle_id) if run is not None and r.per_run_domain else options


# One function per transport: its config section -> its options model (transports.options_class).
LINK_OPTIONS: dict[Transport, Callable[..., TransportOptions]] = {
    Transport.LOCAL: local_options, Transport.ZENOH: zenoh_options, Transport.CAN: can_options,
    Transport.MIXED: mixed_options, Transport.TCP: tcp_options, Transport.ROS2: ros2_options,
}


def link_options(cfg: RunConfig, *, vehicle_id: int, session: str | None = None) -> TransportOptions:
    """The options model of ``cfg.target.transport`` for vehicle ``vehicle_id`` of the
    run with nonce ``session`` (``LINK_OPTIONS``).

    Raises:
        ConfigError: an option the config could not check alone is unusable (a
            password or token not in its environment variable, a domain past 232).
    """
    return LINK_OPTIONS[cfg.target.transport](cfg, vehicle_id=vehicle_id, session=session)


def impair(cfg: RunConfig, link: Link, *, vehicle_id: int, clock: Clock) -> None:
    """Link faults in real time (``target.impair``, adapters/impair.py), if any."""
    from hil.adapters.impair import stage_for

    stage = stage_for(cfg.target.impair, run_seed=cfg.seed, vehicle_id=vehicle_id, clock=clock)
    if stage is not None:
        link.set_impairment(stage)
