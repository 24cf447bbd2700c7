"""The physics process: keeps time and nothing else.

It steps the simulation at wall-clock pace (real time) or as far as the run process
says (lockstep), applies each control the moment it arrives, and at every camera
instant sends the world state to the run process. Each step's lateness (how long
after its due instant it started) goes into a fixed-size histogram.

Messages (``hil.harness.engine.messages``, over one ``multiprocessing`` pipe between
our own processes): ``Start``, ``ApplyControl``, ``Advance``, ``Halt``, ``Exit`` in;
``PhysicsReady``, ``WorldState`` (each camera instant), ``Applied`` (each control),
``Finished`` (after the last step; controls still apply) and ``Done`` (the lateness
histogram and the final state) out; ``RenderJob`` to the render workers.
"""

from __future__ import annotations

import gc
import os
import select
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from hil.harness.engine.messages import (Advance, Applied, ApplyControl, Done, Exit, Finished, Halt, PhysicsReady,
                                         RenderJob, Start, WorldState, encode)
from hil.harness.engine.procs import Origin, ask_realtime
from hil.harness.engine.rings import Ring, RingSpec

SPIN_NS = 60_000          # spin the last 60 µs before a due instant (sleep overshoots)
BIN_NS = 10_000           # lateness histogram resolution: 10 µs
BINS = 10_000             # up to 100 ms; beyond goes to the last bin (max kept exactly)
FINISHED_RETRY_S = 0.005  # a shard's ring full at the end: Finished tried again this often
OVER_10MS_NS = 10_000_000


@dataclass(frozen=True)
class PhysicsSpec:
    """What the physics process needs; pickled once at start."""

    world: Any                      # hil.scenarios.world.WorldSpec
    rules: Any                      # hil.scenarios.ground_truth.RefStateRules
    realtime: bool
    total_steps: int
    wall_per_step_ns: float
    period_steps: int
    phases: tuple[int, ...]         # capture phase (steps) of each ego, in 0..period-1
    late_tolerance_ns: int
    realtime_priority: int
    assign: tuple[int, ...] = ()    # render worker (index into the job rings) of each ego
    spin_ns: int = SPIN_NS          # busy-wait this long before each due instant (sleep overshoots)
    fallback_nice: int = 0          # asked for where SCHED_FIFO is refused (engine.fallback_nice)
    cpu: int | None = None          # the core the physics keeps to itself (engine.physics_cpu)
    offsets: tuple[int, ...] = (0,)  # each rig camera's trigger after camera 0 (steps); (0,): one camera
    dropped: int = 0                # bit mask of rig cameras that never trigger (engine.faults.drop_camera)


Captures = tuple[tuple[int, ...], tuple[int, ...]]  # (egos, the bit mask of each one's cameras that capture)


def capture_table(period_steps: int, phases: tuple[int, ...], offsets: tuple[int, ...] = (0,),
                  dropped: int = 0) -> dict[int, Captures]:
    """Step-in-period -> the egos (indices) that capture at that step and, for each,
    the bit mask of its rig's cameras that do (camera k triggers ``offsets[k]``
    steps after the ego's phase; one camera: mask 1; the cameras of ``dropped``
    never)."""
    out: dict[int, dict[int, int]] = {}
    for vi, p in enumerate(phases):
        for k, off in enumerate(offsets):
            if dropped >> k & 1:
                continue
            at = out.setdefault((p + off) % period_steps, {})
            at[vi] = at.get(vi, 0) | (1 << k)
    return {step: (tuple(m), tuple(m.values())) for step, m in out.items()}


def spread_phases(n: int, period_steps: int) -> tuple[int, ...]:
    """Capture phases spread evenly over the camera period (no capture burst)."""
    return tuple((i * period_steps) // max(n, 1) for i in range(n))


class LatenessHistogram:
    """Per-step lateness in 10 µs bins up to 100 ms, the exact maximum, and the count
    over the late tolerance and over 10 ms. Fixed memory whatever the run length."""

    def __init__(self, *, tolerance_ns: int) -> None:
        self.counts = np.zeros(BINS, np.int64)
        self.tolerance_ns = tolerance_ns
        self.n = 0
        self.late = 0
        self.over_10ms = 0
        self.max_ns = 0

    def add(self, lateness_ns: int) -> None:
        self.n += 1
        self.counts[min(lateness_ns // BIN_NS, BINS - 1)] += 1
        if lateness_ns > self.tolerance_ns:
            self.late += 1
            if lateness_ns > OVER_10MS_NS:
                self.over_10ms += 1
        if lateness_ns > self.max_ns:
            self.max_ns = lateness_ns

    def quantile_ns(self, q: float) -> int:
        """Upper edge of the bin holding quantile ``q`` (0..1); 0 with no steps."""
        if self.n == 0:
            return 0
        k = int(np.searchsorted(np.cumsum(self.counts), max(1, int(np.ceil(q * self.n)))))
        return min((k + 1) * BIN_NS, self.max_ns) if k < BINS - 1 else self.max_ns

    def to_json(self) -> dict[str, Any]:
        nz = np.flatnonzero(self.counts)
        return {"steps": self.n, "late_steps": self.late, "steps_over_10ms": self.over_10ms,
                "tolerance_ns": self.tolerance_ns, "max_ns": self.max_ns,
                "p50_ns": self.quantile_ns(0.5), "p99_ns": self.quantile_ns(0.99),
                "p999_ns": self.quantile_ns(0.999), "bin_ns": BIN_NS,
                "bins": {int(k): int(self.counts[k]) for k in nz}}


@dataclass(frozen=True)
class PhysicsOutputs:
    """Where the physics process writes: rings it never waits on
    (``hil.harness.engine.rings``); a consumer that falls behind loses records, each
    counted in its ring (and in ``Done``'s ``behind``)."""

    run: RingSpec                  # the run process: every world state, the answers, the end
    jobs: tuple[RingSpec, ...]     # one per render worker: its egos' render jobs
    # Shards in processes of their own (hil.harness.engine.shard_proc): each gets the
    # world states of its egos' camera instants (every state in lockstep, and every
    # one with a collision) and its egos' answers in its own ring, and sends its
    # controls on its own pipe. ``shard_of``: the shard of each ego (empty: none).
    shards: tuple[RingSpec, ...] = ()
    shard_of: tuple[int, ...] = ()
    controls: tuple[Connection, ...] = ()


def physics_main(conn: Connection, outputs: PhysicsOutputs, spec: PhysicsSpec, origin: Origin) -> None:
    """Entry point of the physics process. ``conn`` brings the run's commands (and
    takes ``PhysicsReady``); everything else goes out through ``outputs``: each
    render worker gets the world state of its vehicles' camera instants directly."""
    origin.adopt()
    scheduling = ask_realtime(spec.realtime_priority, fallback_nice=spec.fallback_nice, cpu=spec.cpu)
    spins = owns_core(spec.cpu)
    if spins and spec.realtime:
        scheduling += ", spinning between steps"
    from hil.scenarios.sim import Simulation  # no renderer here: physics only

    sim = Simulation(spec.world, rules=spec.rules)
    run = Ring.open(outputs.run, producer=True)
    jobs = [Ring.open(j, producer=True) for j in outputs.jobs]
    shards = [Ring.open(r, producer=True) for r in outputs.shards]
    keeper = _Keeper(conn, run, jobs, sim, spec, shards=shards, shard_of=outputs.shard_of,
                     controls=list(outputs.controls), spins=spins)
    gc.collect()
    gc.freeze()
    gc.disable()  # the loop makes no reference cycles; a collection would be a stall
    conn.send(PhysicsReady(scheduling))
    try:
        keeper.serve()
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        pass
    finally:
        conn.close()
        os._exit(0)


def owns_core(cpu: int | None) -> bool:
    """Whether this process runs on core ``cpu`` alone (``engine.physics_cpu`` granted):
    then the physics spins between steps instead of sleeping. The core is its own, so
    the spin takes nothing from anyone, and a core that never idles is never woken late:
    on a VM, sleeping between steps made 1 % of the steps 2 ms late at 64 vehicles
    (bench/README, GPU host)."""
    try:
        return cpu is not None and os.sched_getaffinity(0) == {cpu}
    except (OSError, AttributeError):
        return False


class _Keeper:
    def __init__(self, conn: Connection, run: Ring, jobs: list[Ring], sim: Any, spec: PhysicsSpec, *,
                 shards: list[Ring], shard_of: tuple[int, ...], controls: list[Connection],
                 spins: bool = False) -> None:
        self.conn, self.run, self.jobs, self.sim, self.spec = conn, run, jobs, sim, spec
        self.spins = spins
        self.shards, self.shard_of = shards, shard_of
        self.egos: tuple[str, ...] = sim.egos
        self.table = capture_table(spec.period_steps, spec.phases, spec.offsets, spec.dropped)
        self.hist = LatenessHistogram(tolerance_ns=spec.late_tolerance_ns)
        self.halted = False
        self.exiting = False
        self.span_ns = 0
        # What brings controls: the run's pipe, and each shard's (until its end closes).
        self.inputs: dict[int, Connection] = {conn.fileno(): conn, **{c.fileno(): c for c in controls}}

    # -- messages ---------------------------------------------------------------

    def _ready(self, timeout_s: float | None) -> list[Connection]:
        """The inputs with a message waiting (up to ``timeout_s``; None: until one)."""
        return [self.inputs[fd] for fd in select.select(list(self.inputs), [], [], timeout_s)[0]]

    def _serve(self, ready: list[Connection]) -> None:
        """One message from each input in ``ready``. A shard's closed pipe is dropped
        (its shard is gone); the run's raises EOFError (the run is gone: leave)."""
        for c in ready:
            try:
                msg = c.recv()
            except EOFError:
                if c is self.conn:
                    raise
                del self.inputs[c.fileno()]
                continue
            self._handle(msg)

    def _handle(self, msg: object) -> None:
        match msg:
            case ApplyControl():
                self._apply(msg)
            case Halt():
                self.halted = True
            case Exit():
                self.halted = self.exiting = True

    def _apply(self, c: ApplyControl) -> None:
        self.sim.set_control(self.egos[c.vi], steering_rad=c.steering_rad, throttle=c.throttle, brake=c.brake)
        t_apply = time.monotonic_ns()
        steps, qpos, qvel = self.sim.state()
        k = self.shard_of[c.vi] if self.shard_of else -1
        (self.run if k < 0 else self.shards[k]).write(encode(Applied(c.vi, c.frame_id, t_apply, steps, qpos, qvel)))

    def _drain(self) -> None:
        while ready := self._ready(0):
            self._serve(ready)

    def _publish(self, caps: Captures, t_state_ns: int) -> None:
        """A camera instant: the state to the render workers first (capture latency),
        then to the run process (truth)."""
        vis, masks = caps
        steps, qpos, qvel = self.sim.state()
        by_worker: dict[int, list[int]] = {}
        for i, vi in enumerate(vis):
            by_worker.setdefault(self.spec.assign[vi], []).append(i)
        unrendered: list[int] = []
        for w, mine in by_worker.items():
            job = RenderJob(steps, qpos, qvel, tuple(vis[i] for i in mine), t_state_ns, tuple(masks[i] for i in mine))
            if not self.jobs[w].write(encode(job)):
                unrendered += job.vis  # that worker is behind: these frames will not come
        collisions = tuple(self.sim.take_collisions())
        state = encode(WorldState(vis, t_state_ns, steps, qpos, qvel, collisions, tuple(unrendered), masks))
        self.run.write(state)
        if self.shards:
            wanted = (range(len(self.shards)) if collisions or not self.spec.realtime
                      else {self.shard_of[vi] for vi in vis})
            for k in wanted:
                self.shards[k].write(state)

    def _send_last(self, msg: Finished | Done, *, to: list[Ring] | None = None) -> None:
        """The end of the run: no deadline left, so wait for room (up to 10 s)."""
        data = encode(msg)
        for ring in to or [self.run]:
            for _ in range(10_000):
                if ring.write(data, count=False):
                    break
                time.sleep(0.001)
            else:
                ring.write(data)  # counted: its consumer is gone or stuck

    def behind(self) -> dict[str, int]:
        """Records each consumer's ring could not take, by consumer name."""
        return {r.name: r.dropped for r in (self.run, *self.jobs, *self.shards) if r.dropped}

    # -- the loops ----------------------------------------------------------------

    def serve(self) -> None:
        msg = self.conn.recv()
        if not isinstance(msg, Start):
            return  # Exit before the start
        start = time.monotonic_ns()
        if self.spec.realtime:
            start = msg.wall_start_ns
            self._realtime(start)
        else:
            self._lockstep()
        self.span_ns = time.monotonic_ns() - start
        self._send_last(Finished(self.sim.steps))
        # To the shards too: after it a shard knows every world state it will get is in.
        # A shard that fell behind has no room yet: tried again every few ms while the
        # controls of the drain are served (they never wait on it).
        finished = encode(Finished(self.sim.steps))
        behind = list(self.shards)
        while not self.exiting:  # the run drains its frames: controls still apply
            behind = [r for r in behind if not r.write(finished, count=False)]
            self._serve(self._ready(FINISHED_RETRY_S if behind else None))
        steps, qpos, qvel = self.sim.state()
        # span_ns: the physics's own wall time from start to its last step (its pace).
        done = Done({**self.hist.to_json(), "span_ns": self.span_ns, "behind": self.behind()}, steps, qpos, qvel,
                    tuple(self.sim.take_collisions()))
        self._send_last(done, to=self.shards)  # after their last answers: the shards know they have all
        self._send_last(done)

    def _realtime(self, start_ns: int) -> None:
        sim, spec, clock = self.sim, self.spec, time.monotonic_ns
        period, table, wps, spin, spins = spec.period_steps, self.table, spec.wall_per_step_ns, spec.spin_ns, self.spins
        while sim.steps < spec.total_steps and not self.halted:
            due = start_ns + int(sim.steps * wps)
            now = clock()
            while now < due:
                wait = due - now
                if spins:  # no sleep: each control still applied at once
                    if ready := self._ready(0):
                        self._serve(ready)
                elif wait > spin and (ready := self._ready((wait - spin) / 1e9)):
                    self._serve(ready)  # a control: applied at once
                now = clock()
            self.hist.add(now - due)
            self._drain()
            vis = table.get(sim.steps % period)
            if vis is not None:
                self._publish(vis, now)
            sim.step()

    def _lockstep(self) -> None:
        sim, spec = self.sim, self.spec
        while not self.halted:
            msg = self.conn.recv()
            if not isinstance(msg, Advance):
                self._handle(msg)
                continue
            for c in msg.controls:
                self._apply(c)
            to_step = min(msg.to_step, spec.total_steps)
            while sim.steps < to_step:
                sim.step()
            if sim.steps >= spec.total_steps:
                return
            self._publish(self.table.get(sim.steps % spec.period_steps, ((), ())), time.monotonic_ns())
