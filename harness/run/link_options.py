"""What a run's config says about one vehicle's link: the target's command line, the
Zenoh key prefix and the TCP token of the run, each transport's link options, and the
link faults to inject. Shared by the per-vehicle launch (``target_launch``) and the shared target."""

from __future__ import annotations

from hil.adapters.link import Link
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


def zenoh_options(cfg: RunConfig, vehicle_id: int, session: str | None = None) -> dict[str, object]:
    """Keyword options of the Zenoh link of one vehicle (``target.zenoh``)."""
    z = cfg.target.zenoh
    return {"connect": [substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.connect],
            "listen": [substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.listen],
            "mode": z.mode.value, "key_prefix": run_key_prefix(cfg, session), "multicast_scouting": z.multicast_scouting,
            "congestion_control": z.congestion_control.value, "lease_ms": z.lease_ms,
            "tls": dict(z.tls) if z.tls else None, **({"usrpwd": z.auth.usrpwd()} if z.auth else {})}


def tcp_token(cfg: RunConfig) -> str | None:
    """The token a TCP target must prove (PROTOCOL.md 4.8): the one in
    ``target.tcp.token_env``, else a fresh per-run secret when the harness starts the
    target itself, else None (``target.tcp.auth: none``: always None).

    Raises:
        ConfigError: ``token_env`` names an unset variable, or a token under 16 bytes.
    """
    from hil.adapters.auth import new_token, token_from_env

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
    as ``hil.adapters.tcp.TcpLink`` takes it, the token and the expected name."""
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
