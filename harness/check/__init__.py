"""Proof runs: ``hil calibrate`` (the harness against a target with injected, known timing
truth) and ``hil target-check`` (any target against PROTOCOL.md)."""
