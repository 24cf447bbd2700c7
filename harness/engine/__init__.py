"""The run's processes, cut by time criticality (DESIGN.md "Processes: who keeps time").

* ``physics``  — the only process with deadlines: it paces the simulation to the
  harness clock, applies controls the moment they arrive (stamping ``t_apply``) and
  publishes the world state at each camera instant (stamping ``t_state``). Nothing
  else runs there: no rendering, no I/O but one pipe, no recording, no analysis.
* ``render``   — a pool of worker processes, each with its own MuJoCo mirror and
  EGL context, that render, encode and (optionally) segment the cameras of the
  vehicles assigned to it. Images travel to the links through shared memory.
* the run process (``hil.harness.run.loop``) — links to the targets (receipt stamped by the
  transport, kernel timestamps where the socket gives them), recording, timing
  analysis and the detector, all fed by bounded queues.

Lockstep runs on the same processes: the run process tells the physics process how
far to step and which controls to apply first, so lockstep stays deterministic.
The physics and render processes are forks of a fork server of the run process that
imported their modules once (``procs.child_context``; ``hil run`` starts it while it
loads its config). Every child dies with the run process (``PR_SET_PDEATHSIG``; a fork
server's children through the server, which ends with the run process); shared memory is
unlinked on close and, if the run process is killed, by multiprocessing's resource
tracker.
"""
