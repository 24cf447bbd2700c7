"""The can transport: a device on a CAN FD bus (DBC frames, ISO-TP for the rest).

``link`` the harness half (``CanLink``, ``CanHalf``) · ``target`` the device half
(``serve_endpoint``) · ``options`` (``CanOptions``, the buses accepted) · ``bus``
opening a vehicle's bus · ``peer`` one side on an open bus (reader, ISO-TP, heartbeats) ·
``dbc`` frames <-> messages (``hil.dbc``) · ``capacity`` what a real bus carries.
"""
