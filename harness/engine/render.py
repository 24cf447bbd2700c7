"""Render workers: each a process with its own MuJoCo mirror of the world and its own
EGL context, serving the cameras of the vehicles assigned to it.

A job is a world state the physics process itself writes at a camera instant into
the worker's ring (``hil.harness.engine.rings``: so a capture never waits behind the
run process, and the physics never waits for a worker) and the egos to capture. The
worker renders each camera, stamps ``t0`` when the pixels are ready, encodes, and
writes the bytes into that vehicle's shared-memory slot ring (images never cross a
pipe); then, with ``truth.visible_boxes``, it renders segmentation for the camera
truth of each camera it drew — after every frame of the job is out, so truth adds
no capture latency.

Worker -> run messages (``hil.harness.engine.messages``): ``WorkerReady``,
``FrameReady`` (the frame's stamps and its slot), ``CameraTruthReady``,
``WorkerFailed``. The run process sends ``StopWorker`` (or just goes away).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from multiprocessing import shared_memory
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from hil.harness.engine.messages import (CameraTruthReady, FrameReady, RenderJob, Warm, WorkerFailed, WorkerReady,
                                         decode)
from hil.harness.engine.procs import Origin
from hil.harness.engine.rings import Ring, RingSpec

SLOTS = 8  # frames of one camera in flight between a worker and the links


def encode_image(rgb: np.ndarray, *, jpeg: bool, quality: int) -> tuple[bytes | np.ndarray, int]:
    """An RGB8 render as the wire carries it: JPEG bytes at ``quality``, or the raw
    array. Returns (data, wire encoding value: 1 RGB8, 2 JPEG)."""
    if jpeg:
        import cv2

        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), (cv2.IMWRITE_JPEG_QUALITY, quality))
        if not ok:  # pragma: no cover - OpenCV failing to encode a valid array
            raise RuntimeError("JPEG encoding failed")
        return buf, 2
    return rgb, 1


@dataclass(frozen=True)
class RenderSpec:
    world: Any                     # hil.scenarios.world.WorldSpec
    vehicles: tuple[str, ...]      # the cameras this worker serves
    shm: dict[str, str]            # vehicle -> shared-memory block name
    slot_bytes: int
    jpeg: bool
    jpeg_quality: int
    visible_boxes: bool
    min_visible_px: int
    delay_ns: int = 0              # injected fault: hold a frame this long before t0 ...
    delay_every: int = 1           # ... every this many frames of a camera (engine.faults)
    out_of: dict[str, int] | None = None  # vehicle -> its shard's pipe (index into render_main's ``outs``)
    cameras: int = 1               # cameras of each vehicle's rig
    fail_at: int = 0               # injected fault: raise on this frame of a camera (1-based; 0: never)


def slot_of(frame: int, camera: int, cameras: int) -> int:
    """The slot of a camera's ``frame``-th image in its vehicle's ring (``SLOTS``
    images of each of the rig's ``cameras``)."""
    return (frame % SLOTS) * cameras + camera


class FrameSlots:
    """One vehicle's ring of ``SLOTS`` image slots per camera in shared memory (run
    side owns and unlinks it)."""

    def __init__(self, *, slot_bytes: int, name: str | None = None, cameras: int = 1) -> None:
        self.slot_bytes = slot_bytes
        create = name is None
        n = SLOTS * cameras
        self.shm = shared_memory.SharedMemory(name=name, create=create, size=slot_bytes * n if create else 0)
        self.owner = create
        self.buf = np.ndarray((n, slot_bytes), np.uint8, buffer=self.shm.buf)

    def write(self, slot: int, data: bytes | np.ndarray) -> int:
        flat = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray)) else data.reshape(-1)
        n = flat.size
        self.buf[slot, :n] = flat
        return n

    def read(self, slot: int, nbytes: int) -> bytes:
        return self.buf[slot, :nbytes].tobytes()

    def close(self) -> None:
        shm = getattr(self, "shm", None)
        if shm is None:
            return
        self.shm = None  # type: ignore[assignment]
        del self.buf
        shm.close()
        if self.owner:
            try:
                shm.unlink()
            except FileNotFoundError:
                pass


class InjectedRenderFault(RuntimeError):
    """``engine.faults.render_fail_at_frame``: the worker fails as a crashing renderer
    would (reported like any failure, without a traceback: nothing to debug)."""


def _hold(ns: int) -> None:
    """The injected render delay: sleep, then spin the last 0.2 ms (sleep overshoots)."""
    end = time.monotonic_ns() + ns
    if ns > 200_000:
        time.sleep((ns - 200_000) / 1e9)
    while time.monotonic_ns() < end:
        pass


def render_main(conn: Connection, jobs: RingSpec, spec: RenderSpec, origin: Origin,
                outs: tuple[Connection, ...] = ()) -> None:
    """Entry point of a render worker: jobs from the physics process in the ring
    ``jobs``, results (and ``StopWorker``) with the run process on ``conn``; the
    frames of a vehicle whose shard runs in a process of its own go to that shard's
    pipe in ``outs`` (``spec.out_of``)."""
    from multiprocessing.connection import wait

    origin.adopt()
    # On the capture path: served before the targets and the run's analysis where the
    # harness may (root). Set before the GL context, so its render threads inherit it.
    from hil.adapters.process import prioritise_this_thread

    prioritise_this_thread()
    import cv2

    # One OpenCV thread: the workers are the parallelism. A pool per worker (a thread
    # per core, spinning between calls) only competes with the other workers, the
    # targets and the physics: a 320x240 encode is no faster with it (bench/README).
    cv2.setNumThreads(1)
    slots: dict[str, FrameSlots] = {}
    try:
        from hil.scenarios.sim import Simulation

        sim = Simulation(spec.world)
        sim.open_renderer()
        # The first render compiles shaders and the first encode sets the encoder up:
        # both happen here, not on the run's first frame.
        for name in spec.vehicles:
            for k in range(spec.cameras):
                encode_image(sim.render(name, k), jpeg=spec.jpeg, quality=spec.jpeg_quality)
                if spec.visible_boxes:
                    sim.camera_truth(name, k, min_visible_px=spec.min_visible_px)
        slots = {v: FrameSlots(slot_bytes=spec.slot_bytes, name=spec.shm[v], cameras=spec.cameras)
                 for v in spec.vehicles}
    except Exception as err:  # noqa: BLE001 - reported to the run, which raises SimulationError
        conn.send(WorkerFailed(f"render worker could not start: {err}"))
        os._exit(1)
    counter = {(v, k): 0 for v in spec.vehicles for k in range(spec.cameras)}
    ring = Ring.open(jobs, producer=False)
    to = {v: outs[spec.out_of[v]] if spec.out_of else conn for v in spec.vehicles}
    conn.send(WorkerReady(os.getpid(), gl_renderer()))
    status = 0
    try:
        while True:
            ready = wait([jobs.bell, conn])
            if conn in ready:
                msg = conn.recv()
                if isinstance(msg, Warm):
                    _warm(sim, spec, msg.until_ns)
                    continue
                break  # StopWorker (the run process gone: EOFError)
            records = ring.read()
            if not records and ring.closed_by_producer:
                break  # the physics is gone
            for record in records:
                _render_job(decode(record), to, sim, slots, counter, spec)  # type: ignore[arg-type]
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        pass
    except Exception as err:  # noqa: BLE001 - the run must hear why, not only that the worker is gone
        if not isinstance(err, InjectedRenderFault):
            import traceback

            traceback.print_exc()
        status = 1
        try:
            conn.send(WorkerFailed(f"render worker {os.getpid()} failed: {type(err).__name__}: {err}"))
        except OSError:
            pass
    finally:
        ring.close()
        for s in slots.values():
            s.close()
        sim.close()
        os._exit(status)


def gl_renderer() -> str:
    """The current OpenGL context's renderer (``GL_RENDERER``: "llvmpipe (LLVM 15.0.6,
    256 bits)", "NVIDIA H200/PCIe/SSE2"); empty where it cannot be read."""
    try:
        from OpenGL import GL

        name = GL.glGetString(GL.GL_RENDERER)
    except Exception:  # noqa: BLE001 - PyOpenGL missing or no current context: unknown, not an error
        return ""
    return name.decode(errors="replace") if isinstance(name, bytes) else ""


def _warm(sim: Any, spec: RenderSpec, until_ns: int) -> None:
    """Render the worker's cameras in turn until ``until_ns`` (``Warm``)."""
    cams = [(name, k) for name in spec.vehicles for k in range(spec.cameras)]
    i = 0
    while cams and time.monotonic_ns() < until_ns:
        sim.render(*cams[i % len(cams)])
        i += 1


def _render_job(job: RenderJob, to: dict[str, Connection], sim: Any, slots: dict[str, FrameSlots],
                counter: dict[tuple[str, int], int], spec: RenderSpec) -> None:
    """Render, stamp, encode and hand over the frames of one job (each vehicle's rig
    cameras of the job in camera order); then the camera truth (segmentation) of each
    of those cameras, in the same order, which adds no capture latency there."""
    steps = job.steps
    sim.load_state(steps, job.qpos, job.qvel)
    names = [sim.egos[vi] for vi in job.vis]
    masks = job.masks or (1,) * len(names)
    for name, mask in zip(names, masks):
        for k in range(spec.cameras):
            if not mask >> k & 1:
                continue
            rgb = sim.render(name, k)
            i = counter[(name, k)]
            if i + 1 == spec.fail_at:
                raise InjectedRenderFault(f"injected fault (engine.faults.render_fail_at_frame): frame {i + 1} of {name}")
            if spec.delay_ns and i % spec.delay_every == 0:
                _hold(spec.delay_ns)
            t0 = time.monotonic_ns()
            data, enc = encode_image(rgb, jpeg=spec.jpeg, quality=spec.jpeg_quality)
            slot = slot_of(i, k, spec.cameras)
            counter[(name, k)] = i + 1
            n = slots[name].write(slot, data)
            to[name].send(FrameReady(name, steps, job.t_state_ns, sim.speed_mps(name), t0, time.monotonic_ns(), slot,
                                     n, enc, k))
    if spec.visible_boxes:
        for name, mask in zip(names, masks):
            for k in range(spec.cameras):
                if mask >> k & 1:
                    to[name].send(CameraTruthReady(name, steps, sim.camera_truth(
                        name, k, min_visible_px=spec.min_visible_px), k))
