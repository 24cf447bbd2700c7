"""Running one run: the driver (start targets, warm up clock sync, run, shut down), the sim loop
that moves frames, estimates and controls, target launch (one process per vehicle or
shared), lockstep latency profiles, and per-vehicle bookkeeping."""
