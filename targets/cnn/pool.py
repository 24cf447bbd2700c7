"""More than one core for the CNN target's CPU side: decoding a batch's frames and
making the nets' inputs on several workers.

A batch's frames are spread over the workers (frame i to worker i mod W); each
worker decodes its frames (``hil.adapters.sdk.decode_image``) and writes the inputs
the batch needs (``Layout``: the detector's and steering net's uint8 images, or the
decoded frame for preprocessing on the device) into slot i of a shared buffer, so
the batch's inputs lie contiguous, in frame order, ready for the nets. The same
function (``prepare_into``) fills the slots in process, on threads and in worker
processes, so every path gives the nets the same bytes.

* ``ProcessPool``: W worker processes (``python -m hil.targets.cnn.decode_worker``).
  Requests go over a pipe per worker (a fixed header and the frame's bytes, never
  pickle), replies (slot, status) over another; the slots are one anonymous
  ``memfd`` mapping both sides share, so decoded pixels are never copied between
  processes. A worker leaves when its request pipe closes (``close``), dies with
  the target (``PR_SET_PDEATHSIG``) and ignores SIGINT (the target handles it).
* ``ThreadPool``: W threads in the target's process, into a private buffer (OpenCV
  releases the interpreter lock while it decodes and resizes; the Python around it
  does not).

Both raise ``PoolError`` when a worker is gone; the target then decodes in process.
"""

from __future__ import annotations

import mmap
import os
import select
import struct
import subprocess
import sys
import threading
from collections.abc import Collection, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from hil.adapters.process import die_with_parent, end_process
from hil.adapters.sdk import decode_image
from hil.adapters.wire.messages import Frame
from hil.common.errors import ProtocolError
from hil.targets.cnn.preprocess import DET_H, DET_W, STEER_H, STEER_W, detector_input, steering_input

# slot, outputs (bit k: output k of the layout), encoding, width, height, cy, fy, pitch, bytes that follow
REQUEST = struct.Struct("<IIIIIdddI")
# slot, status (STATUS_*), byte offset of a protocol error, message bytes that follow
REPLY = struct.Struct("<IIII")
READY_SLOT = 0xFFFFFFFF  # a worker's first reply: it has mapped the slots
STATUS_OK, STATUS_PROTOCOL, STATUS_VALUE, STATUS_OTHER = 0, 1, 2, 3
START_TIMEOUT_S = 60.0


class PoolError(RuntimeError):
    """A worker is gone or did not start: the pool cannot serve any more."""


@dataclass(frozen=True)
class Layout:
    """What a worker makes of each frame: named uint8 images of fixed shapes
    (``det`` and ``steer``: the nets' inputs; ``frame``: the decoded HxWx3 BGR frame)."""

    outputs: tuple[tuple[str, tuple[int, ...]], ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.outputs)

    def spec(self) -> str:
        """``det:120x160x3,steer:66x200x3`` (the worker's command line)."""
        return ",".join(f"{n}:{'x'.join(map(str, shape))}" for n, shape in self.outputs)

    @classmethod
    def parse(cls, text: str) -> Layout:
        """Raises: ValueError: not a ``spec()`` of known outputs."""
        outputs = []
        for part in text.split(","):
            name, _, dims = part.partition(":")
            if name not in ("det", "steer", "frame") or not dims:
                raise ValueError(f"layout {text!r}: expected name:HxWx3 parts of det, steer, frame")
            outputs.append((name, tuple(int(d) for d in dims.split("x"))))
        return cls(tuple(outputs))

    def nbytes(self, slots: int) -> int:
        return slots * sum(int(np.prod(shape)) for _, shape in self.outputs)

    def views(self, buf: mmap.mmap | bytearray, slots: int) -> dict[str, np.ndarray]:
        """One (slots, *shape) uint8 array per output over ``buf``, output after
        output, so any first n slots of an output are one contiguous batch."""
        out, offset = {}, 0
        for name, shape in self.outputs:
            arr = np.ndarray((slots, *shape), np.uint8, buffer=buf, offset=offset)
            out[name] = arr
            offset += arr.nbytes
        return out


NETS = Layout((("det", (DET_H, DET_W, 3)), ("steer", (STEER_H, STEER_W, 3))))


def frame_layout(width: int, height: int) -> Layout:
    """The decoded frame itself (preprocessing on the device)."""
    return Layout((("frame", (height, width, 3)),))


def prepare_into(views: Mapping[str, np.ndarray], slot: int, frame: Frame, names: Collection[str]) -> None:
    """Decode ``frame`` and write the outputs ``names`` into ``slot`` of ``views``.

    Raises:
        ProtocolError, ValueError: the image does not decode (or, for ``frame``, is
            not the slots' size).
    """
    bgr = decode_image(frame)
    for name in names:
        if name == "det":
            views[name][slot] = detector_input(bgr)
        elif name == "steer":
            views[name][slot] = steering_input(bgr, frame.camera.cy, frame.camera.fy, frame.camera.pitch_rad)
        else:
            dst = views[name][slot]
            if dst.shape != bgr.shape:
                raise ValueError(f"a {frame.width}x{frame.height} frame in a pool of "
                                 f"{dst.shape[1]}x{dst.shape[0]} frames")
            dst[...] = bgr


def _raise(status: int, offset: int, message: str) -> None:
    if status == STATUS_PROTOCOL:
        raise ProtocolError(message.removesuffix(f" (at byte offset {offset})"), offset=offset)
    if status == STATUS_VALUE:
        raise ValueError(message)
    raise RuntimeError(message)


def read_exact(fd: int, n: int) -> bytes | None:
    """``n`` bytes from ``fd``; None at end of file before the first byte.

    Raises:
        PoolError: the end came in the middle."""
    parts, got = [], 0
    while got < n:
        chunk = os.read(fd, n - got)
        if not chunk:
            if got:
                raise PoolError(f"pipe closed after {got} of {n} bytes")
            return None
        parts.append(chunk)
        got += len(chunk)
    return parts[0] if len(parts) == 1 else b"".join(parts)


def write_all(fd: int, *bufs: bytes | memoryview) -> None:
    """Write every byte of ``bufs`` (a write may be cut short by a signal)."""
    views = [memoryview(b).cast("B") for b in bufs]
    while views:
        done = os.writev(fd, views)
        while views and done >= len(views[0]):
            done -= len(views[0])
            views.pop(0)
        if views:
            views[0] = views[0][done:]


class ThreadPool:
    """``workers`` threads of this process fill a private buffer of ``slots`` slots."""

    kind = "thread"

    def __init__(self, workers: int, *, slots: int, layout: Layout = NETS) -> None:
        if workers < 1 or slots < 1:
            raise ValueError(f"a pool of {workers} workers and {slots} slots: expected >= 1 of each")
        self.workers, self.slots, self.layout = workers, slots, layout
        self.views = layout.views(bytearray(layout.nbytes(slots)), slots)
        self._exec: ThreadPoolExecutor | None = ThreadPoolExecutor(workers, thread_name_prefix="cnn-decode")

    def prepare(self, frames: Sequence[Frame], names: Collection[str]) -> dict[str, np.ndarray]:
        """The outputs ``names`` of ``frames`` (n x shape arrays over the pool's slots,
        valid until the next call).

        Raises:
            ProtocolError, ValueError: a frame does not decode (the first in order).
            PoolError: the pool is closed.
        """
        if self._exec is None:
            raise PoolError("the decode pool is closed")
        n = len(frames)
        if n > self.slots:
            raise ValueError(f"{n} frames for a pool of {self.slots} slots")
        views = self.views
        futures = [self._exec.submit(prepare_into, views, i, f, names) for i, f in enumerate(frames)]
        errors = [err for err in (fut.exception() for fut in futures) if err is not None]
        if errors:
            raise errors[0]
        return {name: views[name][:n] for name in names}

    def close(self) -> None:
        ex, self._exec = self._exec, None
        if ex is not None:
            ex.shutdown(wait=True)


@dataclass
class _Worker:
    proc: subprocess.Popen[bytes]
    req: int
    rep: int


class ProcessPool:
    """``workers`` worker processes fill ``slots`` slots of a shared ``memfd``.

    Raises:
        PoolError: a worker did not start (its exit code in the message).
        OSError: no pipes, memory or processes left.
    """

    kind = "process"

    def __init__(self, workers: int, *, slots: int, layout: Layout = NETS) -> None:
        if workers < 1 or slots < 1:
            raise ValueError(f"a pool of {workers} workers and {slots} slots: expected >= 1 of each")
        self.workers, self.slots, self.layout = workers, slots, layout
        self._workers: list[_Worker] = []
        self._lock = threading.Lock()
        size = layout.nbytes(slots)
        fd = os.memfd_create("hil-cnn-decode", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, size)
            self._mm: mmap.mmap | None = mmap.mmap(fd, size)
            self.views = layout.views(self._mm, slots)
            try:
                for _ in range(workers):
                    self._spawn(fd, size)
                for k, w in enumerate(self._workers):
                    self._ready(k, w)
            except BaseException:
                self.close()
                raise
        finally:
            os.close(fd)

    @property
    def pids(self) -> list[int]:
        return [w.proc.pid for w in self._workers]

    def _spawn(self, shm_fd: int, size: int) -> None:
        req_r, req_w = os.pipe()
        rep_r, rep_w = os.pipe()
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "hil.targets.cnn.decode_worker", str(req_r), str(rep_w), str(shm_fd),
                 str(size), self.layout.spec(), str(self.slots)],
                pass_fds=(req_r, rep_w, shm_fd), stdin=subprocess.DEVNULL, preexec_fn=die_with_parent)
        except OSError:
            for fd in (req_r, req_w, rep_r, rep_w):
                os.close(fd)
            raise
        os.close(req_r)
        os.close(rep_w)
        self._workers.append(_Worker(proc, req_w, rep_r))

    def _ready(self, k: int, w: _Worker) -> None:
        ready, _, _ = select.select([w.rep], [], [], START_TIMEOUT_S)
        rep = read_exact(w.rep, REPLY.size) if ready else None
        if rep is None or REPLY.unpack(rep)[0] != READY_SLOT:
            code = w.proc.poll()
            raise PoolError(f"decode worker {k} did not start "
                            + (f"(exit code {code}; its error is in this log)" if code is not None
                               else f"within {START_TIMEOUT_S:g} s"))

    def prepare(self, frames: Sequence[Frame], names: Collection[str]) -> dict[str, np.ndarray]:
        """As ``ThreadPool.prepare``.

        Raises:
            ProtocolError, ValueError: a frame does not decode (the first in order).
            PoolError: a worker is gone (the pool is closed then) or the pool is closed.
        """
        n = len(frames)
        if n > self.slots:
            raise ValueError(f"{n} frames for a pool of {self.slots} slots")
        mask = sum(1 << k for k, name in enumerate(self.layout.names) if name in names)
        with self._lock:
            if self._mm is None:
                raise PoolError("the decode pool is closed")
            errors: list[tuple[int, int, int, str]] = []
            try:
                workers = self._workers
                for i, f in enumerate(frames):
                    cam = f.camera
                    head = REQUEST.pack(i, mask, int(f.encoding), f.width, f.height, cam.cy, cam.fy, cam.pitch_rad,
                                        len(f.data))
                    write_all(workers[i % len(workers)].req, head, f.data)
                for k, w in enumerate(workers):
                    for _ in range(len(range(k, n, len(workers)))):
                        rep = read_exact(w.rep, REPLY.size)
                        if rep is None:
                            raise PoolError(f"decode worker {k} (pid {w.proc.pid}) is gone")
                        slot, status, offset, size = REPLY.unpack(rep)
                        text = (read_exact(w.rep, size) or b"") if size else b""
                        if status != STATUS_OK:
                            errors.append((slot, status, offset, text.decode("utf-8", "replace")))
            except (OSError, PoolError) as err:
                self._close_locked()
                raise err if isinstance(err, PoolError) else PoolError(f"decode pool: {err}") from err
        if errors:
            _raise(*min(errors)[1:])
        return {name: self.views[name][:n] for name in names}

    def close(self) -> None:
        """Close the request pipes (each worker leaves at their end), wait for the
        workers (SIGTERM, then SIGKILL, if one lingers). Idempotent."""
        with self._lock:
            self._close_locked()

    def _close_locked(self) -> None:
        workers, self._workers = self._workers, []
        for w in workers:
            os.close(w.req)
        for w in workers:
            end_process(w.proc, grace_s=2.0, term_s=1.0)
            os.close(w.rep)
        mm, self._mm = getattr(self, "_mm", None), None
        self.views = {}
        if mm is not None:
            try:
                mm.close()
            except BufferError:  # a caller still holds a batch's arrays: unmapped when they go
                pass


Pool = ThreadPool | ProcessPool
