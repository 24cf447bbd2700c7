"""The mixed transport: camera frames over Zenoh, everything else on a CAN bus.

``link`` the harness half (``MixedLink``: a ``CanHalf`` and a ``ZenohHalf``) ·
``target`` the device half (``serve_endpoint``) · ``options`` (``MixedOptions``: the
zenoh and can transports' own).
"""
