"""Harness: the simulator loop, the run driver, the recorder, reports and the CLI."""

__version__ = "0.1.0"
