"""Starting and reaching a run's targets: one link per vehicle, built from the
``target:`` config, plus the locally started target process where the transport
does not start one itself (zenoh, can, mixed, tcp and ros2 with a ``command``)."""

from __future__ import annotations

import os
import queue
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.adapters.link import Link, Received, open_link
from hil.adapters.process import die_with_parent, end_process
from hil.common.errors import TargetError, TransportError
from hil.harness.config.model import RunConfig, Transport
from hil.harness.run.link_options import impair, link_options, target_command
from hil.timing.clock import Clock

SYNC_WARMUP_SAMPLES = 8  # clock-sync exchanges each link makes before the run


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
              rx: queue.Queue[Received] | None = None, session: str | None = None,
              can_tap: Callable[[Any, int, bool], None] | None = None) -> tuple[Link, TargetProcess | None]:
    """Build (not open) the link of one vehicle, starting its local target process
    first where a network transport has a ``command``: the transport's options model
    from its config section (``link_options``), opened by ``open_link``. A ``mixed``
    target takes frames over ``target.zenoh`` and answers over ``target.can``;
    ``can_tap`` sees every CAN frame of a ``can`` or ``mixed`` link (the run's bus log).

    Raises:
        TargetError: the command cannot be started.
        TransportError / ConfigError: the transport options are unusable.
    """
    t = cfg.target
    if t.shared:  # one process for all vehicles (harness/run/shared_target.py)
        from hil.harness.run.shared_target import shared_link

        return shared_link(cfg, vehicle_id=vehicle_id, clock=clock, out_dir=out_dir, rx=rx)  # type: ignore[return-value]
    log = out_dir / f"target-{vehicle}.log"
    options = link_options(cfg, vehicle_id=vehicle_id, session=session)  # the run's own keys, token, domain
    if t.transport == Transport.LOCAL:  # the link starts its target itself
        link = open_link(t.transport, vehicle_id=vehicle_id, clock=clock, rx_queue=rx, options=options,
                         command=target_command(cfg, vehicle_id=vehicle_id), log_path=log)
        impair(cfg, link, vehicle_id=vehicle_id, clock=clock)
        return link, None
    # What the target is told (its run's keys, credentials, token, DDS domain; never recorded).
    env = {**({"HIL_SESSION": session} if session else {}), **options.child_env()}
    proc = TargetProcess(target_command(cfg, vehicle_id=vehicle_id), log_path=log, env=env) if t.command else None
    # The run's hooks a link takes besides its options: the bus log of a CAN bus, and for
    # tcp, to stop waiting once the target this run started is gone.
    hooks: dict[Transport, dict[str, object]] = {Transport.TCP: {"abandon": _exited(proc)},
                                                 Transport.CAN: {"tap": can_tap}, Transport.MIXED: {"tap": can_tap}}
    try:
        link = open_link(t.transport, vehicle_id=vehicle_id, clock=clock, rx_queue=rx, options=options,
                         **hooks.get(t.transport, {}))
    except BaseException:
        if proc is not None:
            proc.close()
        raise
    link.give_up_when(_exited(proc))  # a started target that died will never say hello
    impair(cfg, link, vehicle_id=vehicle_id, clock=clock)
    return link, proc


def open_links(links: list[tuple[str, Link, TargetProcess | None]], *, timeout_s: float) -> None:
    """Open every link at once: the local targets are spawned here, one after
    another (each process dies with the thread that spawned it, so with this one),
    then every HELLO is awaited together, so N targets start in the time of the
    slowest, not the sum (issue 24, item 4).

    Raises:
        TargetError: a target could not start or did not say hello in time; the
            message names its vehicle (the first in order) and, for a process the
            harness started that is gone, its exit code and log.
        TransportError: a transport could not connect.
    """
    for name, link, proc in links:
        if link.transport_name == "local":
            try:
                link.start()
            except TargetError as err:
                raise TargetError(f"{name}: {err}{exit_note(proc)}") from err

    errors: list[BaseException | None] = [None] * len(links)

    def one(k: int) -> None:
        name, link, proc = links[k]
        try:
            link.open(hello_timeout_s=timeout_s)
        except (TargetError, TransportError) as err:
            errors[k] = TargetError(f"{name}: {err}{exit_note(proc)}")
        except Exception as err:  # noqa: BLE001 - raised below, in vehicle order
            errors[k] = err

    # Daemon threads: a run interrupted meanwhile closes the links, which ends their waits.
    threads = [threading.Thread(target=one, args=(k,), name=f"hil-open-{k}", daemon=True) for k in range(len(links))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for failed in errors:
        if failed is not None:
            raise failed


def close_links(links: list[Link]) -> None:
    """Close every link at once (each says BYE and waits a moment for its target to
    leave): N links end in the time of the slowest, not the sum (~33 ms each here)."""
    threads = [threading.Thread(target=link.close, name=f"hil-close-{k}", daemon=True)
               for k, link in enumerate(links)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def exit_note(proc: object) -> str:
    """'; the target process exited with code N: <its log's last lines>' for a target
    the harness started that is gone, else ''."""
    code = proc.exited() if proc is not None and hasattr(proc, "exited") else None
    if code is None:
        return ""
    tail = proc.log_tail()  # type: ignore[attr-defined]
    return f"; the target process it started exited with code {code}" + (f": {tail}" if tail else "")


def check_identity(cfg: RunConfig, vehicles: list[Any], procs: list[Any]) -> None:
    """The run measures the target it started or was told to reach, no other.

    Raises:
        TargetError: a target the harness started is gone although something answered
            (another process on its endpoint), or a HELLO names another target than
            ``target.expect_name``.
    """
    for p in procs:
        if hasattr(p, "exited") and p.exited() is not None:
            raise TargetError("another target answered on the endpoint, but the target this run started is gone"
                              f"{exit_note(p)} — refusing to measure a target it did not start (is a leftover "
                              "target or another run using the port?)")
    want = cfg.target.expect_name
    for v in vehicles:
        got = v.link.hello.target_name if v.link.hello is not None else ""
        if want is not None and not got.startswith(want):
            raise TargetError(f"{v.name}: the target that answered says it is {got!r}, not {want!r} "
                              "(target.expect_name) — refusing to measure it")


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
