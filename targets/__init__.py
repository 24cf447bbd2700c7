"""Example AI targets. They see only what the wire carries: never scenarios or harness.

- ``targets.echo``: a fixed answer after a set busy time (transport and timing floor).
- ``targets.cv_baseline``: a classical OpenCV driver (colour-blob vehicle detection,
  pinhole ranging, SAFE/SLOW/STOP rules, lane keeping); ``python -m targets.cv_baseline``.
"""
