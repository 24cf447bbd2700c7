"""How long the rest of some work will take at the pace so far (``hil train``,
``hil study``, ``hil compare``: ``hil.harness.report.progress.WorkProgress``)."""

from __future__ import annotations


def time_left(done: float, total: float, elapsed_s: float) -> str:
    """What is left at the pace so far: ``about 2.5 min left`` (``estimating`` before
    anything is done; ``done`` at the end)."""
    if done >= total:
        return "done"
    if done <= 0 or elapsed_s <= 0:
        return "estimating the time left"
    left = elapsed_s / done * (total - done)
    if left < 90:
        return f"about {max(1, round(left))} s left"
    return f"about {left / 60:.1f} min left" if left < 5400 else f"about {left / 3600:.1f} h left"


__all__ = ["time_left"]
