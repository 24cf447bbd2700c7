"""The local transport: the target is a child process on this machine.

The harness creates a connected Unix stream socket pair and starts the target
command with one end inherited; the descriptor number is in ``HIL_LOCAL_FD``.
Messages travel back-to-back on the stream (PROTOCOL.md section 10.1). The child's
stdout and stderr go to a log file so a failure can be explained in one line.

Camera frames of ``LocalOptions.shm_inline_below`` bytes and more go through shared
memory when the target says it can read them (``hil.adapters.local.shm``: a ring of
slots in an anonymous segment whose descriptor is in ``HIL_LOCAL_SHM``; HELLO
capability bit 0); the socket then carries a 32-byte notice in place of the frame. A frame larger than a
slot, and every frame to a target without the capability, goes inline.

The harness half, ``LocalLink``; the child's half, ``serve_endpoint``, is in
``hil.adapters.local.target`` (used by ``hil.adapters.sdk.serve``).
"""

from __future__ import annotations

import os
import queue
import socket
import subprocess
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, NoReturn

from hil.adapters.link import Link, Received
from hil.adapters.local.options import ENV_FD, LocalOptions
from hil.adapters.local.shm import ENV_SHM, SHM_FRAMES, ShmRing
from hil.adapters.process import die_with_parent, end_process, prioritise_this_thread
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import Hello, MsgType
from hil.adapters.wire.receipt import ReaderStats, StreamReader
from hil.common.errors import TargetError, TransportError
from hil.timing.clock import Clock

_SOCK_BUF = 4 * 1024 * 1024


@dataclass
class LocalStats:
    """Counters only this transport has (the shared ones are in ``LinkStats``)."""

    frames_shm: int = 0  # FRAMEs sent through a shared-memory slot
    frames_inline: int = 0  # FRAMEs sent on the socket
    too_big_for_slot: int = 0  # of those, the ones a slot could not hold
    overwritten_unread: int = 0  # slots reused before the target had read them (frames it never saw)


class LocalLink(Link):
    """Starts ``command`` as a child process and talks to it over a socket pair.

    Args:
        command: the target program and its arguments.
        options: the shared-memory frame ring (``LocalOptions``; default: offered).
        log_path: receives the child's stdout and stderr.
        env: the child's environment (default: this process's).

    Raises:
        TargetError: empty command. TransportError: bad ring options.
    """

    transport_name = "local"

    def __init__(self, *, command: Sequence[str], vehicle_id: int, clock: Clock, options: LocalOptions | None = None,
                 log_path: str | os.PathLike[str] | None = None, env: Mapping[str, str] | None = None,
                 rx_queue_size: int = 1024, rx_queue: queue.Queue[Received] | None = None) -> None:
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size,
                         rx_queue=rx_queue)
        self._ring: ShmRing | None = None
        self._ring_on = False
        self._send_lock = threading.Lock()
        if not command:
            raise TargetError("target.command is empty; give the program to run")
        o = self.options = options or LocalOptions()
        if o.shm_inline_below < 0:
            raise TransportError(f"shm_inline_below={o.shm_inline_below}: expected a byte count >= 0")
        ShmRing.check_options(slots=o.shm_slots, slot_bytes=o.shm_slot_bytes)
        self.command = list(command)
        self.log_path = Path(log_path) if log_path else None
        self._env = dict(env) if env else None
        self._inline_below = max(o.shm_inline_below, protocol.HEADER_SIZE)
        self.local_stats = LocalStats()
        self.receipt_stats = ReaderStats()  # how each message's receipt was stamped (hil.adapters.wire.receipt)
        self._opened_ns = 0
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        self._reader: threading.Thread | None = None
        self._log: BinaryIO | None = None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc else None

    @property
    def shm_active(self) -> bool:
        """True once the target has accepted the shared-memory ring (after ``open``)."""
        return self._ring_on

    def open(self, *, hello_timeout_s: float) -> Hello:
        hello = super().open(hello_timeout_s=hello_timeout_s)
        if self._ring is not None and hello.capabilities & SHM_FRAMES:
            self._ring_on = True
        elif self._ring is not None:  # the target cannot read it: free the memory now
            self._ring.close()
            self._ring = None
        return hello

    def _socket_and_ring(self) -> socket.socket:
        """Make the frame ring (if asked for and possible) and the socket pair; keeps
        our end and returns the target's."""
        if self.options.shm:
            try:
                self._ring = ShmRing(slots=self.options.shm_slots, slot_bytes=self.options.shm_slot_bytes)
            except TransportError as err:  # an optimisation only: frames go inline
                self.stats.last_error = f"no shared-memory frame ring, frames go inline: {err}"
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        for s in (ours, theirs):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCK_BUF)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _SOCK_BUF)
        self._sock = ours
        return theirs

    def _open(self) -> None:
        self._opened_ns = self.clock.now_ns()  # before the child can write a byte
        theirs = self._socket_and_ring()
        env = dict(os.environ if self._env is None else self._env)
        env[ENV_FD] = str(theirs.fileno())
        env.pop(ENV_SHM, None)
        pass_fds = [theirs.fileno()]
        if self._ring is not None:
            env[ENV_SHM] = str(self._ring.fd)
            pass_fds.append(self._ring.fd)
        env.setdefault("PYTHONUNBUFFERED", "1")
        out: int | BinaryIO = subprocess.DEVNULL
        if self.log_path is not None:
            self._log = open(self.log_path, "ab")  # noqa: SIM115 (closed in _close_transport)
            out = self._log
        try:
            self._proc = subprocess.Popen(self.command, pass_fds=pass_fds, env=env,
                                          stdin=subprocess.DEVNULL, stdout=out, stderr=out,
                                          start_new_session=True, preexec_fn=die_with_parent)
        except FileNotFoundError as err:
            raise TargetError(f"target command not found: {self.command[0]!r} "
                              f"(check target.command)") from err
        except PermissionError as err:
            raise TargetError(f"target command is not executable: {self.command[0]!r}") from err
        except OSError as err:  # e.g. ENOEXEC: a script without '#!', a binary for another machine
            raise TargetError(f"target command {self.command[0]!r} cannot be started: {err.strerror or err} "
                              f"(a script needs a '#!' line; a program must be built for this machine)") from err
        finally:
            theirs.close()
            if self._ring is not None:
                self._ring.release_fd()  # the child has its own; our mapping stays
        self._reader = threading.Thread(target=self._read_loop, name=f"local-rx-{self.vehicle_id}",
                                        daemon=True)
        self._reader.start()

    def _read_loop(self) -> None:
        sock = self._sock
        if sock is None:  # closed before this thread first ran (a stop while the target starts)
            return
        prioritise_this_thread()  # receipt stamps must not wait behind analysis or recording
        reader: StreamReader[NoReturn] = StreamReader(sock, self.clock, stats=self.receipt_stats,
                                                      not_before_ns=self._opened_ns)  # a message a read
        self._read_stream(reader, failed=lambda err: f"socket error: {err}", ended=self._exit_reason)

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
        sock = getattr(self, "_sock", None)
        if sock is None:
            raise TransportError("local link is not open")
        is_frame = len(data) >= protocol.HEADER_SIZE and data[5] == MsgType.FRAME and data[:4] == protocol.MAGIC
        try:
            with self._send_lock:  # a notice must follow its slot write, never overtake it
                sock.sendall(self._frame_wire(data) if is_frame else data)
        except OSError as err:
            self._mark_gone(f"send failed: {err}")
            raise TransportError(f"cannot send to the local target: {err}") from err

    def _frame_wire(self, data: bytes) -> bytes:
        """What goes on the socket for one FRAME: a notice, with the message in a slot,
        or the message itself."""
        ring, st = self._ring, self.local_stats
        if self._ring_on and ring is not None and len(data) >= self._inline_below:
            if ring.fits(len(data)):
                overwritten = ring.stats.overwritten_unread
                notice = ring.put(data)
                st.overwritten_unread += ring.stats.overwritten_unread - overwritten
                st.frames_shm += 1
                return notice
            st.too_big_for_slot += 1
        st.frames_inline += 1
        return data

    def _close_transport(self) -> None:
        sock, self._sock = getattr(self, "_sock", None), None
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        # The target got BYE and EOF; give it a moment, then end it by PID.
        end_process(getattr(self, "_proc", None))
        reader = getattr(self, "_reader", None)
        if reader is not None and reader is not threading.current_thread():
            reader.join(timeout=2.0)
        with self._send_lock:  # no slot write in progress
            self._ring_on = False
            ring, self._ring = getattr(self, "_ring", None), None
        if ring is not None:
            ring.close()  # anonymous memory: gone once the child's mapping is gone too
        log = getattr(self, "_log", None)
        if log is not None:
            self._log = None
            log.close()


__all__ = ["LocalLink", "LocalStats"]
