"""Analysis of a run while it goes: the timing observer (clock sync, anomalies), the corner-case
detector and its observer, late-reaction physics, and the summary written at the end."""
