"""Reports people read: the HTML run report with its plots, corner cases and fleet view, and
``hil compare`` (two runs against tolerances)."""
