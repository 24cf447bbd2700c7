"""``Engine``: the physics process and the render pool of one run, seen from the run
process. A context manager; ``close()`` is idempotent, ends every child (by PID) and
unlinks the shared memory."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from typing import Any, TypeVar

from hil.common.errors import SimulationError
from hil.harness.engine.messages import (Advance, ApplyControl, Exit, Halt, PhysicsReady, Start, StopWorker, Warm,
                                         WorkerFailed, WorkerReady)
from hil.harness.engine.physics import PhysicsOutputs, PhysicsSpec, physics_main
from hil.harness.engine.procs import Origin, Pump, RingPump, child_context, end_child, widen_pipe
from hil.harness.engine.render import FrameSlots, RenderSpec, render_main
from hil.harness.engine.rings import Ring, RingSpec

START_TIMEOUT_S = 60.0
WARM_NS = 300_000_000  # engine.render_warm_ms "auto" on a GPU
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software rasterizer")  # Mesa's, in GL_RENDERER
RING_BYTES = 4 << 20  # each of the physics's rings: ~2,000 world states of a 16-vehicle scene
_M = TypeVar("_M")


def auto_workers(n_vehicles: int) -> int:
    """Render workers when the config says 0: one per spare core, at most one per
    vehicle (the physics process and the run process keep a core between them)."""
    return max(1, min(n_vehicles, (os.cpu_count() or 2) - 1))


def warm_lead_ns(setting: str | int, renderers: list[str]) -> int:
    """How long the render workers warm up before a real-time start
    (``engine.render_warm_ms``): "auto" warms where a worker renders on hardware (its
    ``GL_RENDERER`` known and not one of Mesa's software renderers)."""
    if setting != "auto":
        return int(setting) * 1_000_000
    hardware = any(r and not any(sw in r.lower() for sw in SOFTWARE_RENDERERS) for r in renderers)
    return WARM_NS if hardware else 0


@contextlib.contextmanager
def without_main_module() -> Iterator[None]:
    """While starting children: hide ``__main__``'s file and spec, so a spawned child
    does not import the caller's main script (it needs only our modules). A user's
    script that calls ``execute`` without an ``if __name__ == "__main__"`` guard
    would otherwise run again in every child."""
    main = sys.modules.get("__main__")
    saved: dict[str, Any] = {k: main.__dict__[k] for k in ("__file__", "__spec__")
                             if main is not None and k in main.__dict__}
    try:
        if main is not None:
            main.__dict__.pop("__file__", None)
            main.__dict__["__spec__"] = None
        yield
    finally:
        if main is not None:
            main.__dict__.pop("__spec__", None)
            main.__dict__.update(saved)


@dataclass(frozen=True)
class ShardIO:
    """A shard process's ends of the engine: its ring from the physics (states and
    answers), its pipe to the physics (controls), its pipe from each render worker
    (frames, camera truth), and the shared-memory frame slots of its vehicles."""

    ring: RingSpec
    control: Connection
    frames: tuple[Connection, ...]
    shm: dict[str, str]
    slot_bytes: int
    cameras: int = 1


class Engine:
    """Starts the children; once :meth:`connect` names the run's handlers, their
    messages (``hil.harness.engine.messages``) go there, on the threads that read them."""

    def __init__(self, *, physics: PhysicsSpec, render: RenderSpec, workers: int, ring_bytes: int = RING_BYTES,
                 stall_run: tuple[int, float] | None = None, shard_of: tuple[int, ...] = (),
                 render_warm: str | int = "auto") -> None:
        """``stall_run``: (step, seconds): the injected stuck consumer
        (``engine.faults.stall_run_ms``, see ``RingPump``). ``shard_of``: the shard
        process of each ego when the run's vehicles live in shards of their own
        (empty: in this process); their ends are :meth:`shard_io`."""
        self._procs: list[Any] = []
        self._conns: list[Any] = []
        self.slots: dict[str, FrameSlots] = {}
        self.scheduling = "not started"
        self.worker_pids: list[int] = []
        self.renderers: list[str] = []  # each worker's GL_RENDERER
        self.warm_ns = 0  # render_warm: how long the workers warm up before a real-time start
        self.rings: list[Ring] = []
        self._pumps: list[Pump | RingPump] = []
        self._stall = stall_run
        self.shard_of = shard_of
        self._shard_ends: list[ShardIO] = []
        ctx = child_context()
        origin = Origin.here()  # this thread: the physics's core kept off (keep_off_core)
        names = render.vehicles
        n_shards = max(shard_of, default=-1) + 1
        try:
            self.slots = {v: FrameSlots(slot_bytes=render.slot_bytes, cameras=render.cameras) for v in names}
            shm = {v: s.shm.name for v, s in self.slots.items()}
            self.workers = max(1, min(workers, len(names)))
            self.assign = {v: i % self.workers for i, v in enumerate(names)}
            self._render: list[Any] = []
            # The physics writes into rings it never waits on: one per render worker
            # (its jobs), one for this process (world states, answers, the end).
            self.rings = [Ring.create(f"render-{w}", capacity=ring_bytes) for w in range(self.workers)]
            self._run_ring = Ring.create("run", capacity=ring_bytes)
            self.rings.append(self._run_ring)
            # A shard in its own process: a ring from the physics (its egos' states and
            # answers), a pipe to it (its controls), a pipe from each render worker.
            shard_rings = [Ring.create(f"shard-{k}", capacity=ring_bytes) for k in range(n_shards)]
            self.rings += shard_rings
            controls = [ctx.Pipe(duplex=False) for _ in range(n_shards)]
            frames = [[ctx.Pipe(duplex=False) for _ in range(n_shards)] for _ in range(self.workers)]
            for w in range(self.workers):
                mine = tuple(v for v in names if self.assign[v] == w)
                rs = replace(render, vehicles=mine, shm={v: shm[v] for v in mine},
                             out_of={v: shard_of[names.index(v)] for v in mine} if n_shards else None)
                a, b = ctx.Pipe()
                for c in (a, b, *(c for pair in frames[w] for c in pair)):
                    widen_pipe(c)
                outs = tuple(wr for _rd, wr in frames[w])
                rp = ctx.Process(target=render_main, args=(b, self.rings[w].consumer_spec(), rs, origin, outs),
                                 name=f"hil-render-{w}", daemon=True)
                with without_main_module():
                    rp.start()
                b.close()
                for _rd, wr in frames[w]:
                    wr.close()
                self._procs.append(rp)
                self._render.append(a)
            physics = replace(physics, assign=tuple(self.assign[v] for v in names))
            outputs = PhysicsOutputs(run=self._run_ring.producer_spec(),
                                     jobs=tuple(r.producer_spec() for r in self.rings[:self.workers]),
                                     shards=tuple(r.producer_spec() for r in shard_rings), shard_of=shard_of,
                                     controls=tuple(rd for rd, _wr in controls))
            pc, cc = ctx.Pipe()
            widen_pipe(pc)
            widen_pipe(cc)
            p = ctx.Process(target=physics_main, args=(cc, outputs, physics, origin), name="hil-physics",
                            daemon=True)
            with without_main_module():
                p.start()
            cc.close()
            for rd, _wr in controls:
                rd.close()
            for r in self.rings:  # the children hold their ends now: a child's exit reads as end of file
                r.release(producer=True, consumer=r not in (self._run_ring, *shard_rings))
            self._shard_ends = [ShardIO(ring=shard_rings[k].consumer_spec(), control=controls[k][1],
                                        frames=tuple(frames[w][k][0] for w in range(self.workers)),
                                        shm={v: shm[v] for i, v in enumerate(names) if shard_of[i] == k},
                                        slot_bytes=render.slot_bytes, cameras=render.cameras)
                                for k in range(n_shards)]
            self._procs.append(p)
            self._physics = pc
            self._conns = [pc, *self._render]
        except BaseException:
            self.close()
            raise
        self._render_warm = render_warm
        self._ready = False

    def wait_ready(self) -> None:
        """Wait until the physics and every render worker have started (imports, MuJoCo,
        the GL context). The constructor only starts them, so that what starts beside
        them (the targets) overlaps their start-up; :meth:`connect` and :meth:`start`
        wait here first if nobody did. Idempotent.

        Raises:
            SimulationError: a child failed or did not start within ``START_TIMEOUT_S``
                (the engine is closed then).
        """
        if self._ready:
            return
        try:
            self.scheduling = self._expect(self._physics, PhysicsReady, "physics").scheduling
            for w, c in enumerate(self._render):
                ready = self._expect(c, WorkerReady, f"render worker {w}")
                self.worker_pids.append(ready.pid)
                self.renderers.append(ready.renderer)
            self.warm_ns = warm_lead_ns(self._render_warm, self.renderers)
        except BaseException:
            self.close()
            raise
        self._ready = True

    @staticmethod
    def _expect(conn: Any, kind: type[_M], who: str) -> _M:
        if not conn.poll(START_TIMEOUT_S):
            raise SimulationError(f"{who} did not start within {START_TIMEOUT_S:.0f} s")
        try:
            msg = conn.recv()
        except EOFError as err:
            raise SimulationError(f"{who} exited while starting") from err
        if not isinstance(msg, kind):
            raise SimulationError(msg.text if isinstance(msg, WorkerFailed)
                                  else f"{who}: unexpected {type(msg).__name__}")
        return msg

    def shard_io(self, k: int) -> ShardIO:
        """What shard process ``k`` needs from the engine (pass it to the process at
        its start, then :meth:`release_shard_io`)."""
        return self._shard_ends[k]

    def release_shard_io(self) -> None:
        """This process's copies of the shards' ends, closed once their processes
        hold them (so a shard's exit reads as end of file where it matters)."""
        ends, self._shard_ends = self._shard_ends, []
        for io in ends:
            io.control.close()
            for c in io.frames:
                c.close()
        for r in self.rings:
            if r.name.startswith("shard-"):
                r.release(consumer=True)

    def connect(self, *, on_physics: Callable[[Any], None], on_render: Callable[[Any], None]) -> None:
        """Hand every message of the physics (its ring) to ``on_physics`` and of the
        render workers to ``on_render``, each on the thread that reads it."""
        self.wait_ready()
        self._pumps = [RingPump(self._run_ring, on_physics, name="physics", stall=self._stall)]
        self._pumps += [Pump(c, on_render, name=f"render-{w}") for w, c in enumerate(self._render)]

    # -- to the physics process ------------------------------------------------------

    def start(self, wall_start_ns: int, *, warm: bool = False) -> None:
        """Start the physics, paced from ``wall_start_ns``; ``warm``: the render workers
        render their cameras until then (``Warm``)."""
        self.wait_ready()
        if warm:
            for c in self._render:
                c.send(Warm(wall_start_ns))
        self._physics.send(Start(wall_start_ns))

    def control(self, c: ApplyControl) -> None:
        self._physics.send(c)

    def advance(self, to_step: int, controls: tuple[ApplyControl, ...]) -> None:
        self._physics.send(Advance(to_step, controls))

    def halt(self) -> None:
        self._physics.send(Halt())

    def exit_physics(self) -> None:
        self._physics.send(Exit())

    # -- from the render pool ----------------------------------------------------------

    def frame_bytes(self, vehicle: str, slot: int, nbytes: int) -> bytes:
        return self.slots[vehicle].read(slot, nbytes)

    def alive(self) -> bool:
        return all(p.is_alive() for p in self._procs)

    def behind(self) -> dict[str, int]:
        """Records the physics could not hand to each consumer so far (its ring was
        full: the consumer fell behind), by consumer name; only those with losses."""
        out = {}
        for r in self.rings:
            n = r.dropped_now()
            if n:
                out[r.name] = n
        return out

    # -- lifetime ------------------------------------------------------------------------

    def close(self) -> None:
        """End every child (asked first, then terminated, then killed) and unlink the
        shared memory. Idempotent."""
        procs, self._procs = self._procs, []
        for c in getattr(self, "_render", []):
            try:
                c.send(StopWorker())
            except (OSError, ValueError):
                pass
        if procs:
            try:
                self._physics.send(Exit())
            except (OSError, ValueError, AttributeError):
                pass
        for p in procs:
            end_child(p)
        for c in self._conns:
            c.close()
        self._conns = []
        self.release_shard_io()
        for pump in self._pumps:
            pump.join(1.0)
        rings, self.rings = self.rings, []
        for r in rings:
            r.close()
        slots, self.slots = self.slots, {}
        for s in slots.values():
            s.close()

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
