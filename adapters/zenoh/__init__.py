"""The zenoh transport: the target is a host (or process) on a Zenoh network.

``link`` the harness half (``ZenohLink``, ``ZenohHalf``) · ``target`` the device half
(``serve_endpoint``) · ``options`` (``ZenohOptions``, the one home of Zenoh's options:
endpoints, TLS, user/password, the run's own keys and credentials) · ``session`` the
session both halves open (config, keys, bounded close) · ``shared_target`` one
process serving many vehicles.
"""
