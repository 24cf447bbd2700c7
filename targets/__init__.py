"""Example AI targets. They see only what the wire carries: never scenarios or harness.

- ``hil.targets.echo``: a fixed answer after a set busy time (transport and timing floor).
- ``hil.targets.cv_baseline``: a classical OpenCV driver (colour-blob vehicle detection,
  pinhole ranging, SAFE/SLOW/STOP rules, lane keeping); ``python -m hil.targets.cv_baseline``.
- ``hil.targets.cnn``: the paper's AI in torch (detector + steering CNN, pinhole position
  estimation, the same decision rules, baseline fallback, model swap by command);
  ``python -m hil.targets.cnn`` (weights in ``targets/weights``, model card there).
"""
