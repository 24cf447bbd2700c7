"""Timing: clocks, per-frame pipeline records and latency statistics.

Pure computation: integer nanoseconds in, records out. Imports numpy only and
nothing else of ours, so every other package (and the target SDK on a device)
may depend on it.
"""
