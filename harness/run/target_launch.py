"""Starting and reaching a run's targets: one link per vehicle, built from the
``target:`` config, plus the locally started target process where the transport
does not start one itself (zenoh, can, mixed, tcp and ros2 with a ``command``)."""

from __future__ import annotations

import os
import queue
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.adapters.link import Link, Received, open_link
from hil.adapters.process import die_with_parent, end_process
from hil.adapters.wire.auth import ENV_TOKEN
from hil.adapters.zenoh.options import AUTH_ENV
from hil.common.errors import TargetError
from hil.harness.config.model import RunConfig, Transport
from hil.harness.run.link_options import (can_options, impair, ros2_node_env, ros2_options, run_credentials,
                                         run_key_prefix, target_command, tcp_options, tcp_token, zenoh_options)
from hil.timing.clock import Clock


class TargetProcess:
    """A target program the harness started for a network transport. Ended by PID
    (SIGTERM, then SIGKILL) on ``close()``, which is idempotent."""

    def __init__(self, command: list[str], *, log_path: Path, env: dict[str, str] | None = None) -> None:
        self.command = command
        self.log_path = log_path
        self._log = open(log_path, "ab")  # noqa: SIM115 (closed in close())
        try:
            self.proc: subprocess.Popen[bytes] | None = subprocess.Popen(
                command, stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log,
                env=dict(os.environ, PYTHONUNBUFFERED="1", **(env or {})), start_new_session=True,
                preexec_fn=die_with_parent)
        except FileNotFoundError as err:
            self._log.close()
            raise TargetError(f"target command not found: {command[0]!r} (check target.command)") from err
        except PermissionError as err:
            self._log.close()
            raise TargetError(f"target command is not executable: {command[0]!r}") from err
        except OSError as err:  # e.g. ENOEXEC: a script without '#!', a binary for another machine
            self._log.close()
            raise TargetError(f"target command {command[0]!r} cannot be started: {err.strerror or err} "
                              f"(a script needs a '#!' line; a program must be built for this machine)") from err

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def exited(self) -> int | None:
        """The exit code if the process has ended, else None."""
        return None if self.proc is None else self.proc.poll()

    def log_tail(self, lines: int = 3) -> str:
        """The last ``lines`` non-empty lines of its log, joined with ' | '."""
        try:
            with open(self.log_path, "rb") as f:
                f.seek(max(0, self.log_path.stat().st_size - 8192))
                text = f.read().decode("utf-8", "replace")
        except OSError:
            return ""
        return " | ".join(ln.strip() for ln in text.splitlines() if ln.strip())[-600:] if lines else ""

    def close(self) -> None:
        proc, self.proc = getattr(self, "proc", None), None
        if proc is not None and proc.poll() is None and _stopped(proc.pid):
            proc.kill()  # frozen (SIGSTOP): it can neither leave on BYE nor act on SIGTERM
            proc.wait()
        end_process(proc, term_s=3.0)  # it got BYE; let it leave on its own first
        log = getattr(self, "_log", None)
        if log is not None and not log.closed:
            log.close()


def _stopped(pid: int) -> bool:
    """True when process ``pid`` is stopped (state T or t in ``/proc/PID/stat``)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    fields = stat.rpartition(")")[2].split()
    return bool(fields) and fields[0] in ("T", "t")


def make_link(cfg: RunConfig, *, vehicle_id: int, vehicle: str, clock: Clock, out_dir: Path,
              rx: queue.Queue[Received], session: str | None = None,
              can_tap: Callable[[Any, int, bool], None] | None = None) -> tuple[Link, TargetProcess | None]:
    """Build (not open) the link of one vehicle, starting its local target process
    first where a network transport has a ``command``. A ``mixed`` target takes
    frames over ``target.zenoh`` and answers over ``target.can``; ``can_tap`` sees
    every CAN frame of a ``can`` or ``mixed`` link (the run's bus log).

    Raises:
        TargetError: the command cannot be started.
        TransportError / ConfigError: the transport options are unusable.
    """
    t = cfg.target
    if t.shared:  # one process for all vehicles (harness/run/shared_target.py)
        from hil.harness.run.shared_target import shared_link

        return shared_link(cfg, vehicle_id=vehicle_id, clock=clock, out_dir=out_dir, rx=rx)  # type: ignore[return-value]
    log = out_dir / f"target-{vehicle}.log"
    if t.transport == Transport.LOCAL:
        link = open_link("local", command=target_command(cfg, vehicle_id=vehicle_id), vehicle_id=vehicle_id,
                         clock=clock, log_path=log, rx_queue=rx)
        impair(cfg, link, vehicle_id=vehicle_id, clock=clock)
        return link, None
    env = {"HIL_SESSION": session} if session else {}
    creds = None
    if t.transport in (Transport.ZENOH, Transport.MIXED):
        env["HIL_ZENOH_KEY_PREFIX"] = run_key_prefix(cfg, session)
        creds = run_credentials(cfg, session, vehicle_id)  # a third peer gets no session
        if creds is not None:
            env[AUTH_ENV] = ":".join(creds)
    elif t.transport == Transport.ROS2:  # its own domain, Cyclone on loopback, the run's topics
        env.update(ros2_node_env(cfg, vehicle_id, session))
    token = tcp_token(cfg) if t.transport == Transport.TCP else None
    if token is not None:  # the target proves it holds this (PROTOCOL.md 4.8); never recorded
        env[ENV_TOKEN] = token
    proc = TargetProcess(target_command(cfg, vehicle_id=vehicle_id), log_path=log, env=env) if t.command else None
    try:
        if t.transport == Transport.ZENOH:
            link = open_link("zenoh", vehicle_id=vehicle_id, clock=clock, rx_queue=rx,
                             **zenoh_options(cfg, vehicle_id, session, creds))
        elif t.transport == Transport.TCP:  # only the target that proves the token (or names itself as expected)
            link = open_link("tcp", vehicle_id=vehicle_id, clock=clock, rx_queue=rx, abandon=_exited(proc),
                             **tcp_options(cfg, vehicle_id, token))
        elif t.transport == Transport.ROS2:  # target.ros2: a ROS 2 node over Cyclone DDS
            link = open_link("ros2", vehicle_id=vehicle_id, clock=clock, rx_queue=rx,
                             **ros2_options(cfg, vehicle_id, session))
        elif t.transport == Transport.MIXED:  # frames over target.zenoh, the rest over target.can
            link = open_link("mixed", vehicle_id=vehicle_id, clock=clock, rx_queue=rx, tap=can_tap,
                             **zenoh_options(cfg, vehicle_id, session, creds), **can_options(cfg, vehicle_id))
        else:
            link = open_link("can", vehicle_id=vehicle_id, clock=clock, camera_over=t.can.camera_over, rx_queue=rx,
                             tap=can_tap, **can_options(cfg, vehicle_id))
    except BaseException:
        if proc is not None:
            proc.close()
        raise
    impair(cfg, link, vehicle_id=vehicle_id, clock=clock)
    return link, proc


def _exited(proc: TargetProcess | None) -> Callable[[], str | None] | None:
    """For a link that waits for a target this run started: why to stop waiting (its
    process has exited, so whatever answers now is not it), else None."""
    if proc is None:
        return None
    return lambda: "the target process this run started exited" if proc.exited() is not None else None


def can_preflight(cfg: RunConfig, *, frame_bytes: int) -> str:
    """What the CAN bus carries for frames of ``frame_bytes`` (a rendered frame of
    this run, encoded) at the configured bitrates, as one line for the user.

    Raises:
        ConfigError: ``camera.fps`` asks for more than the bus carries.
    """
    from hil.adapters.can.capacity import bus_capacity

    c = cfg.target.can
    report = bus_capacity(bitrate=c.bitrate, data_bitrate=c.data_bitrate, fd=True, frame_bytes=frame_bytes,
                          fps=cfg.camera.fps, camera_over=c.camera_over,
                          sync_hz=cfg.timing.sync.burst / cfg.timing.sync.interval_s)
    report.check()
    return (f"CAN bus {c.bitrate // 1000}k/{c.data_bitrate // 1000}k: {frame_bytes / 1024:.1f} KB frames, "
            f"at most {report.max_fps:.1f} fps; {cfg.camera.fps:g} fps loads the bus {report.load:.0%}")
