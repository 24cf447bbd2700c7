"""What a run's config says about one vehicle's link: the target's command line, the
Zenoh key prefix of the run, each transport's link options, and the link faults to
inject. Shared by the per-vehicle launch (``target_launch``) and the shared target."""

from __future__ import annotations

import secrets

from hil.adapters.link import Link
from hil.harness.config.model import RunConfig, Transport
from hil.harness.config.target import substitute
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
    from hil.adapters.zenoh_options import run_usrpwd

    z = cfg.target.zenoh
    auth = run_usrpwd(*credentials) if credentials else z.auth.usrpwd() if z.auth else None
    return {"connect": [substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.connect],
            "listen": [substitute(e, vehicle_id=vehicle_id, base_port=z.base_port) for e in z.listen],
            "mode": z.mode.value, "key_prefix": run_key_prefix(cfg, session), "multicast_scouting": z.multicast_scouting,
            "congestion_control": z.congestion_control.value, "lease_ms": z.lease_ms,
            "tls": dict(z.tls) if z.tls else None, **({"usrpwd": auth} if auth else {})}


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
