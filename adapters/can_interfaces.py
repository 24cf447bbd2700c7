"""Which python-can interfaces the CAN transport accepts: buses on this machine only.

Every name here drives a CAN adapter attached to this host (or, ``virtual``, a bus
inside one process for tests). python-can's network backends are not listed on
purpose: they carry CAN frames as IP packets to other hosts, and nothing of a run may
leave the machine that way. No imports, so the config check can use it cheaply.
"""

from __future__ import annotations

LOCAL_INTERFACES: tuple[str, ...] = (
    "socketcan", "pcan", "kvaser", "vector", "slcan", "ixxat", "neovi", "gs_usb", "nican", "nixnet",
    "systec", "usb2can", "canalystii", "cantact", "etas", "seeedstudio", "serial", "robotell", "iscan",
    "neousys", "virtual",
)
