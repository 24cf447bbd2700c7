"""``hil study``: a sweep of runs over a parameter (e.g. vehicles), and its report."""
