"""Options of the can transport (no imports, so the config check can use them cheaply).

Which python-can interfaces it accepts: buses on this machine only. Every name here drives a CAN adapter attached to this host (or, ``virtual``, a bus
inside one process for tests). python-can's network backends are not listed on
purpose: they carry CAN frames as IP packets to other hosts, and nothing of a run may
leave the machine that way.
"""

from __future__ import annotations

LOCAL_INTERFACES: tuple[str, ...] = (
    "socketcan", "pcan", "kvaser", "vector", "slcan", "ixxat", "neovi", "gs_usb", "nican", "nixnet",
    "systec", "usb2can", "canalystii", "cantact", "etas", "seeedstudio", "serial", "robotell", "iscan",
    "neousys", "virtual",
)

HEARTBEAT_TIMEOUT_S = 0.75  # three missed heartbeats (every 250 ms): the other side is gone

__all__ = ["HEARTBEAT_TIMEOUT_S", "LOCAL_INTERFACES"]
