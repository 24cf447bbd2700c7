"""The local transport: the target is a child process of the harness, on a socket pair
with camera frames through a shared-memory ring.

``link`` the harness half (``LocalLink``) · ``target`` the child's half
(``serve_endpoint``) · ``options`` (``LocalOptions``) · ``shm`` the frame ring ·
``shared_link`` / ``shared_target`` one child serving every vehicle (a shared target).
"""
