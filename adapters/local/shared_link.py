"""The local transport for a shared target: one child process serves every vehicle.

The harness starts the target once (``SharedLocalTarget``) with one end of a
control socket (``AF_UNIX``, ``SOCK_SEQPACKET``) whose descriptor is in
``HIL_LOCAL_CTL``. Each vehicle's link (``SharedLocalLink``, a ``LocalLink``)
makes its own stream socket pair, and its own shared-memory frame ring where
offered, as a per-vehicle ``LocalLink`` does, and hands the target its ends over
the control socket (``SCM_RIGHTS``): one packet per vehicle, 8 bytes
(``<I vehicle_id, I flags``; flag bit 0: a ring descriptor follows the socket's).
So vehicles can join in any number, one after another, and each vehicle's socket
carries exactly the framing of PROTOCOL.md section 10.1 (HELLO first, notices
for ring frames), as with a target of its own.

The target (``serve_shared``, ``hil.adapters.local.shared_target``) serves each socket
on its own reader thread with a ``BatchedEndpoint`` of one ``BatchScheduler``; it
exits when the control socket closes (the harness is done) and every vehicle's
session has ended. This module is the harness's half.
"""

from __future__ import annotations

import os
import socket
import subprocess
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path

from hil.adapters.batching import ENV_CTL
from hil.adapters.local.link import LocalLink
from hil.adapters.local.shared_target import ATTACH, HAS_RING
from hil.adapters.process import die_with_parent, end_process
from hil.common.errors import TargetError, TransportError


class SharedLocalTarget:
    """The one target process of a shared local target, and its control socket.

    Args:
        command: the program (it must serve ``HIL_LOCAL_CTL``, e.g. ``hil.targets.cnn --shared``).
        log_path: receives its stdout and stderr.
        env: extra environment entries (e.g. ``HIL_BATCH_LOG``).

    Raises:
        TargetError: the command is empty or cannot be started.
    """

    def __init__(self, command: Sequence[str], *, log_path: Path, env: Mapping[str, str] | None = None) -> None:
        if not command:
            raise TargetError("target.command is empty; give the program to run")
        self.command = list(command)
        self.log_path = Path(log_path)
        self._lock = threading.Lock()
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._ctl: socket.socket | None = ours
        full_env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        full_env[ENV_CTL] = str(theirs.fileno())
        for key in ("HIL_LOCAL_FD", "HIL_LOCAL_SHM"):
            full_env.pop(key, None)
        self._log = open(self.log_path, "ab")  # noqa: SIM115 (closed in close())
        try:
            self.proc: subprocess.Popen[bytes] | None = subprocess.Popen(
                self.command, pass_fds=[theirs.fileno()], env=full_env, stdin=subprocess.DEVNULL,
                stdout=self._log, stderr=self._log, start_new_session=True, preexec_fn=die_with_parent)
        except OSError as err:
            ours.close()
            self._ctl = None
            self._log.close()
            what = ("not found" if isinstance(err, FileNotFoundError) else
                    "not executable" if isinstance(err, PermissionError) else f"cannot be started: {err.strerror or err}")
            raise TargetError(f"target command {self.command[0]!r} {what} (check target.command)") from err
        finally:
            theirs.close()

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None

    def attach(self, vehicle_id: int, sock_fd: int, ring_fd: int | None) -> None:
        """Hand the target one vehicle's socket (and ring) descriptors; ours stay open.

        Raises:
            TransportError: the target is gone (its control socket is closed).
        """
        fds = [sock_fd] + ([ring_fd] if ring_fd is not None else [])
        payload = ATTACH.pack(vehicle_id, HAS_RING if ring_fd is not None else 0)
        with self._lock:
            ctl = self._ctl
            if ctl is None:
                raise TransportError("the shared target has been closed")
            try:
                socket.send_fds(ctl, [payload], fds)
            except OSError as err:
                raise TransportError(f"cannot hand vehicle {vehicle_id} to the shared target: {err}") from err

    def close(self) -> None:
        """Close the control socket (the target leaves once its sessions have ended),
        then end the process by PID if it does not. Idempotent."""
        with self._lock:
            ctl, self._ctl = self._ctl, None
        if ctl is not None:
            ctl.close()
        proc, self.proc = getattr(self, "proc", None), None
        end_process(proc, term_s=3.0)
        log = getattr(self, "_log", None)
        if log is not None and not log.closed:
            log.close()


class SharedLocalLink(LocalLink):
    """One vehicle's link to a ``SharedLocalTarget``: a ``LocalLink`` whose socket
    (and ring) go to the running shared process instead of a child of its own.
    Closing it ends this vehicle's session, not the process."""

    def __init__(self, *, host: SharedLocalTarget, **kwargs: object) -> None:
        """``kwargs``: as ``LocalLink`` takes them (``vehicle_id``, ``clock``, ``options``, ...)."""
        super().__init__(command=host.command, log_path=host.log_path, **kwargs)  # type: ignore[arg-type]
        self.host = host

    def _open(self) -> None:
        theirs = self._socket_and_ring()
        self._proc = self.host.proc  # for the exit reason; never ended by this link
        try:
            self.host.attach(self.vehicle_id, theirs.fileno(), None if self._ring is None else self._ring.fd)
        finally:
            theirs.close()
            if self._ring is not None:
                self._ring.release_fd()
        self._reader = threading.Thread(target=self._read_loop, name=f"shared-rx-{self.vehicle_id}", daemon=True)
        self._reader.start()

    def _close_transport(self) -> None:
        self._proc = None  # the process is the host's: it outlives this vehicle's session
        super()._close_transport()


__all__ = ["SharedLocalLink", "SharedLocalTarget"]
