"""The tcp transport: the local transport's stream framing over one TCP connection.

``link`` the harness half (``TcpLink``) · ``target`` the device half
(``serve_endpoint``) · ``options`` (``TcpOptions``, the run's token) · ``handshake``
addresses, socket options and the HELLO/AUTH check before a connection is the run's.
"""
