"""Options of the can transport (no imports, so the config check can use them cheaply).

Which python-can interfaces it accepts: buses on this machine only. Every name here
drives a CAN adapter attached to this host (or, ``virtual``, a bus inside one process
for tests). python-can's network backends are not listed on purpose: they carry CAN
frames as IP packets to other hosts, and nothing of a run may leave the machine that way.
"""

from __future__ import annotations

from dataclasses import dataclass

LOCAL_INTERFACES: tuple[str, ...] = (
    "socketcan", "pcan", "kvaser", "vector", "slcan", "ixxat", "neovi", "gs_usb", "nican", "nixnet",
    "systec", "usb2can", "canalystii", "cantact", "etas", "seeedstudio", "serial", "robotell", "iscan",
    "neousys", "virtual",
)

HEARTBEAT_TIMEOUT_S = 0.75  # three missed heartbeats (every 250 ms): the other side is gone


@dataclass(frozen=True)
class CanOptions:
    """A vehicle's CAN bus, for both halves (the harness's ``CanLink``, a target's
    ``serve_endpoint``) and the run config's ``target.can``.

    Attributes:
        interface, channel: python-can's (a bus on this machine: ``LOCAL_INTERFACES``).
        bitrate, data_bitrate: nominal and CAN FD data bitrates, bit/s (socketcan takes
            them from ``ip link`` instead).
        fd: must be True (the transport's frames are CAN FD).
        camera_over: the harness's camera frames, ``"isotp"`` on this bus or ``"none"``
            (a mixed target takes them over Zenoh).
        heartbeat_timeout_s: silence after which the other side is gone (s).
    """

    interface: str = "socketcan"
    channel: str = "vcan0"
    bitrate: int = 500_000
    data_bitrate: int = 2_000_000
    fd: bool = True
    camera_over: str = "isotp"
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S

    def child_env(self) -> dict[str, str]:
        """Nothing: a CAN target is told its bus on its command line."""
        return {}


__all__ = ["HEARTBEAT_TIMEOUT_S", "LOCAL_INTERFACES", "CanOptions"]
