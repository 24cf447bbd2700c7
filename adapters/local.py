"""The local transport: the target is a child process on this machine.

The harness creates a connected Unix stream socket pair and starts the target
command with one end inherited; the descriptor number is in ``HIL_LOCAL_FD``.
Messages travel back-to-back on the stream (PROTOCOL.md). The child's stdout and
stderr go to a log file so a failure can be explained in one line.
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path

from adapters.link import Link, Received
from timing.clock import Clock
from timing.errors import TargetError, TransportError

ENV_FD = "HIL_LOCAL_FD"
_SOCK_BUF = 4 * 1024 * 1024


class LocalLink(Link):
    """Starts ``command`` as a child process and talks to it over a socket pair.

    ``log_path`` receives the child's stdout and stderr.
    """

    transport_name = "local"

    def __init__(self, *, command: Sequence[str], vehicle_id: int, clock: Clock,
                 log_path: str | os.PathLike[str] | None = None, env: Mapping[str, str] | None = None,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None) -> None:
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size,
                         rx_queue=rx_queue)
        if not command:
            raise TargetError("target.command is empty; give the program to run")
        self.command = list(command)
        self.log_path = Path(log_path) if log_path else None
        self._env = dict(env) if env else None
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        self._reader: threading.Thread | None = None
        self._log = None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc else None

    def _open(self) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        for s in (ours, theirs):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCK_BUF)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _SOCK_BUF)
        self._sock = ours
        env = dict(os.environ if self._env is None else self._env)
        env[ENV_FD] = str(theirs.fileno())
        env.setdefault("PYTHONUNBUFFERED", "1")
        out = subprocess.DEVNULL
        if self.log_path is not None:
            self._log = open(self.log_path, "ab")  # noqa: SIM115 (closed in _close_transport)
            out = self._log
        try:
            self._proc = subprocess.Popen(self.command, pass_fds=(theirs.fileno(),), env=env,
                                          stdin=subprocess.DEVNULL, stdout=out, stderr=out,
                                          start_new_session=True)
        except FileNotFoundError as err:
            raise TargetError(f"target command not found: {self.command[0]!r} "
                              f"(check target.command)") from err
        except PermissionError as err:
            raise TargetError(f"target command is not executable: {self.command[0]!r}") from err
        finally:
            theirs.close()
        self._reader = threading.Thread(target=self._read_loop, name=f"local-rx-{self.vehicle_id}",
                                        daemon=True)
        self._reader.start()

    def _read_loop(self) -> None:
        assert self._sock is not None
        sock = self._sock
        while True:
            try:
                data = sock.recv(1 << 20)
            except OSError as err:
                if not self._closed:
                    self._mark_gone(f"socket error: {err}")
                break
            t_rx = self.clock.now_ns()
            if not data:
                self._mark_gone(self._exit_reason())
                break
            self._on_bytes(data, t_rx)

    def _exit_reason(self) -> str:
        proc = self._proc
        if proc is None:
            return "connection closed"
        try:
            code = proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return "target closed its connection"
        tail = self._log_tail()
        detail = f": {tail}" if tail else ""
        return f"target process exited with code {code}{detail}"

    def _log_tail(self) -> str:
        if self.log_path is None or not self.log_path.exists():
            return ""
        with open(self.log_path, "rb") as f:
            f.seek(max(0, self.log_path.stat().st_size - 4096))
            lines = [ln.strip() for ln in f.read().decode("utf-8", "replace").splitlines() if ln.strip()]
        return lines[-1][:300] if lines else ""

    def _send_bytes(self, data: bytes) -> None:
        if self._sock is None:
            raise TransportError("local link is not open")
        try:
            self._sock.sendall(data)
        except OSError as err:
            self._mark_gone(f"send failed: {err}")
            raise TransportError(f"cannot send to the local target: {err}") from err

    def _close_transport(self) -> None:
        sock, self._sock = getattr(self, "_sock", None), None
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            # The target got BYE and EOF; give it a moment, then end it by PID.
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=2.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        reader = getattr(self, "_reader", None)
        if reader is not None and reader is not threading.current_thread():
            reader.join(timeout=2.0)
        log = getattr(self, "_log", None)
        if log is not None:
            self._log = None
            log.close()
