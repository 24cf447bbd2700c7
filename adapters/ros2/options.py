"""Options of the ``ros2`` transport, with no DDS library: ``Ros2Options`` (the one
home of their defaults: the harness's link and the run config's ``target.ros2`` read
it), topic names, QoS profiles, clock modes, the control mapping's constants,
Cyclone DDS's loopback configuration and the domain a run gives a node it starts
(``Ros2Options.for_run``), told to the node in its environment
(``Ros2Options.child_env``). The config model checks with these before anything opens.

Discovery. Cyclone is configured explicitly (:func:`cyclone_xml`): one interface
(``127.0.0.1`` by default), multicast off, and unicast discovery to an explicit
peer list (``127.0.0.1``), so nothing leaves the machine unless a peer says so. A
node the harness starts gets the same configuration in ``CYCLONEDDS_URI`` and its
domain in ``ROS_DOMAIN_ID`` (:func:`node_env`).
"""

from __future__ import annotations

import ipaddress
import json
import math
import re
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Literal
from xml.sax.saxutils import quoteattr

from hil.common.errors import ConfigError

MAX_DOMAIN_ID = 232  # Cyclone's default port mapping: 7400 + 250 * domain stays below 65536
PER_RUN_DOMAINS = (100, MAX_DOMAIN_ID)  # the range a run draws its nodes' domains from
MAX_AUTO_PARTICIPANTS = 32  # participants per domain per host that unicast discovery probes
RAW_IMAGE_TOPIC = "/camera/image_raw"  # image_transport's names: raw images, JPEG under /compressed
COMPRESSED_IMAGE_TOPIC = f"{RAW_IMAGE_TOPIC}/compressed"
_TOPIC = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


class ClockMode(str, Enum):
    """Which clock the header stamps are on (README, "ROS 2")."""

    SIM = "sim"  # stamps are sim time; the harness publishes /clock (nodes run with use_sim_time)
    SYSTEM = "system"  # stamps are t0 on this host's CLOCK_REALTIME (nodes on their system clock)


class Reliability(str, Enum):
    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"


class History(str, Enum):
    KEEP_LAST = "keep_last"
    KEEP_ALL = "keep_all"


class Durability(str, Enum):
    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"


@dataclass(frozen=True)
class QosProfile:
    """One endpoint's QoS as ROS 2 names it. ``depth``: samples kept (keep_last)."""

    reliability: Reliability = Reliability.RELIABLE
    history: History = History.KEEP_LAST
    depth: int = 10
    durability: Durability = Durability.VOLATILE

    def __post_init__(self) -> None:
        """Names ("reliable", ...) become the enums. Raises ConfigError: a bad value."""
        for name, kind in (("reliability", Reliability), ("history", History), ("durability", Durability)):
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))
            except ValueError:
                valid = ", ".join(k.value for k in kind)
                raise ConfigError(f"QoS {name}={getattr(self, name)!r}: expected one of {valid}") from None
        if not isinstance(self.depth, int) or not 1 <= self.depth <= 10_000:
            raise ConfigError(f"QoS depth={self.depth!r}: expected an integer in 1..10000")


# Images: reliable is offered (a reliable and a best-effort subscriber both match) with a
# short history (a slow subscriber costs old frames, never memory); replies: reliable.
IMAGE_QOS = QosProfile(depth=2)
REPLY_QOS = QosProfile(depth=10)
STATIC_QOS = QosProfile(depth=1, durability=Durability.TRANSIENT_LOCAL)  # /tf_static, as tf2 offers it
CLOCK_QOS = QosProfile(depth=1)


def topic_problem(name: str) -> str | None:
    """Why ``name`` is not a fully qualified ROS 2 topic name (None when it is)."""
    if not isinstance(name, str) or not _TOPIC.match(name):
        return (f"a fully qualified ROS 2 topic name such as '/camera/image_raw' (starts with '/', "
                f"tokens of letters, digits and '_', none starting with a digit), not {name!r}")
    return None


def dds_topic(name: str) -> str:
    """The DDS topic rmw maps ROS 2 topic ``name`` to: ``/x/y`` -> ``rt/x/y``.

    Raises:
        ConfigError: not a fully qualified topic name.
    """
    problem = topic_problem(name)
    if problem is not None:
        raise ConfigError(f"topic: expected {problem}")
    return "rt" + name


def check_domain(domain_id: int) -> int:
    """Raises ConfigError: not a domain id Cyclone can map to ports (0..232)."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise ConfigError(f"domain_id={domain_id!r}: expected an integer in 0..{MAX_DOMAIN_ID}")
    return domain_id


def per_run_domain(session: str, vehicle_id: int) -> int:
    """The domain of vehicle ``vehicle_id``'s node in the run with nonce ``session``
    (hex): in ``PER_RUN_DOMAINS``, distinct per vehicle of a run (up to 133)."""
    lo, hi = PER_RUN_DOMAINS
    return lo + (int(session, 16) + vehicle_id) % (hi - lo + 1)


def cyclone_xml(*, interface: str = "127.0.0.1", peers: tuple[str, ...] = ("127.0.0.1",),
                multicast: bool = False, lease_ms: int = 1000) -> str:
    """Cyclone DDS's configuration for one domain: ``interface`` only, multicast as
    given, unicast discovery to ``peers`` (addresses or host names), and a participant
    lease of ``lease_ms`` (how long a participant that went silent, a killed process,
    stays discovered; Cyclone's default is 10 s).

    Raises:
        ConfigError: an empty interface, no peer while multicast is off, a bad lease.
    """
    if isinstance(lease_ms, bool) or not isinstance(lease_ms, int) or not 100 <= lease_ms <= 600_000:
        raise ConfigError(f"ros2 lease_ms={lease_ms!r}: expected an integer number of ms in 100..600000")
    if not interface:
        raise ConfigError("ros2 interface: expected an address such as 127.0.0.1")
    if not peers and not multicast:
        raise ConfigError("ros2 peers: with multicast off, discovery needs at least one peer (e.g. 127.0.0.1)")
    try:
        ipaddress.ip_address(interface)
        iface = f"<NetworkInterface address={quoteattr(interface)}/>"
    except ValueError:
        iface = f"<NetworkInterface name={quoteattr(interface)}/>"
    peer_xml = "".join(f"<Peer address={quoteattr(p)}/>" for p in peers)
    return ("<CycloneDDS><Domain Id=\"any\"><General>"
            f"<Interfaces>{iface}</Interfaces><AllowMulticast>{str(multicast).lower()}</AllowMulticast>"
            "</General><Discovery>"
            f"<Peers>{peer_xml}</Peers><ParticipantIndex>auto</ParticipantIndex>"
            f"<MaxAutoParticipantIndex>{MAX_AUTO_PARTICIPANTS}</MaxAutoParticipantIndex>"
            f"<LeaseDuration>{lease_ms}ms</LeaseDuration>"
            "</Discovery></Domain></CycloneDDS>")


@dataclass(frozen=True)
class Topics:
    """The ROS 2 topics of a run (fully qualified). ``image``: ``""`` is the default of
    the encoding (``RAW_IMAGE_TOPIC`` or ``COMPRESSED_IMAGE_TOPIC``); ``speed`` and
    ``detections`` may be ``""`` (not published / not read)."""

    image: str = ""
    camera_info: str = "/camera/camera_info"
    speed: str = "/vehicle/twist"
    clock: str = "/clock"
    control: str = "/control/ackermann_cmd"
    detections: str = "/perception/detections"


@dataclass(frozen=True)
class DriveLimits:
    """The constants of the control mapping (``hil.adapters.ros2.answers.DriveMapping``):
    ``max_accel_mps2``/``max_decel_mps2`` scale acceleration to throttle/brake,
    ``speed_gain_per_s`` turns a speed-only command into one, at or below
    ``stop_speed_mps`` (and not accelerating) the state is STOP. Units: m/s^2, 1/s, m/s.

    Raises:
        ConfigError: a value is not a positive number (``stop_speed_mps``: >= 0).
    """

    max_accel_mps2: float = 3.0
    max_decel_mps2: float = 8.0
    speed_gain_per_s: float = 1.0
    stop_speed_mps: float = 0.05

    def __post_init__(self) -> None:
        for name in ("max_accel_mps2", "max_decel_mps2", "speed_gain_per_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"ros2 {name}={v!r}: expected a positive number")
        if not (math.isfinite(self.stop_speed_mps) and self.stop_speed_mps >= 0):
            raise ConfigError(f"ros2 stop_speed_mps={self.stop_speed_mps!r}: expected a number >= 0")


@dataclass(frozen=True)
class Ros2Options:
    """The ros2 link's options (README, "ROS 2"); the SDK's ROS 2 node takes its own
    from its environment, as a ROS 2 node does (``child_env`` writes it).

    Attributes:
        domain_id: the DDS domain (0..232).
        interface, peers, multicast, lease_ms: Cyclone's discovery (``cyclone_xml``).
        clock: ``sim`` (header stamps are sim time, ``/clock`` published) or
            ``system`` (stamps are t0 on this host's system clock).
        compressed: frames go out as ``CompressedImage`` (JPEG), else as ``Image``.
        topics: the topics (``Topics``).
        base_frame, camera_frame, optical_frame: the TF frames of the camera mount.
        mount: the camera's (forward, lateral, height) in m and (pitch, yaw) in rad.
        image_qos, reply_qos: the QoS offered for frames and asked for answers.
        drive: the control mapping's constants (``DriveLimits``).
    """

    domain_id: int = 0
    interface: str = "127.0.0.1"
    peers: tuple[str, ...] = ("127.0.0.1",)
    multicast: bool = False
    lease_ms: int = 1000
    clock: Literal["sim", "system"] = "sim"
    compressed: bool = True
    topics: Topics = field(default_factory=Topics)
    base_frame: str = "base_link"
    camera_frame: str = "camera_link"
    optical_frame: str = "camera_optical_frame"
    mount: tuple[float, float, float, float, float] = (2.3, 0.0, 1.3, 0.0, 0.0)
    image_qos: QosProfile = IMAGE_QOS
    reply_qos: QosProfile = REPLY_QOS
    drive: DriveLimits = field(default_factory=DriveLimits)

    @property
    def image_topic(self) -> str:
        """``topics.image``, or the default of the encoding."""
        return self.topics.image or (COMPRESSED_IMAGE_TOPIC if self.compressed else RAW_IMAGE_TOPIC)

    def cyclone_xml(self) -> str:
        """Cyclone DDS's configuration of these options (``cyclone_xml``).

        Raises:
            ConfigError: as ``cyclone_xml``.
        """
        return cyclone_xml(interface=self.interface, peers=tuple(self.peers), multicast=self.multicast,
                           lease_ms=self.lease_ms)

    def for_run(self, *, session: str, vehicle_id: int) -> Ros2Options:
        """These options for a run whose harness starts its own node: the run's own
        domain (``per_run_domain``), so no other node on the host answers for it."""
        return replace(self, domain_id=per_run_domain(session, vehicle_id))

    def child_env(self) -> dict[str, str]:
        """What a node the harness starts is told (``node_env``: its domain, Cyclone as
        its rmw, Cyclone's configuration), and the run's topics by role for the SDK's
        ROS 2 node (``HIL_ROS2_TOPICS``; a ROS 2 node is remapped by its own launch
        arguments instead).

        Raises:
            ConfigError: a domain past 232, or a bad discovery option.
        """
        t = self.topics
        node = {"compressed_image" if self.compressed else "image": self.image_topic, "camera_info": t.camera_info,
                "speed": t.speed, "control": t.control, "detections": t.detections}
        return {**node_env(self.domain_id, self.cyclone_xml()), "HIL_ROS2_TOPICS": json.dumps(node)}


def node_env(domain_id: int, config_xml: str) -> dict[str, str]:
    """Environment of a ROS 2 node the harness starts: its domain, Cyclone as its rmw,
    and Cyclone's configuration inline (``CYCLONEDDS_URI`` takes XML text)."""
    return {"ROS_DOMAIN_ID": str(check_domain(domain_id)), "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp",
            "CYCLONEDDS_URI": config_xml}


__all__ = ["CLOCK_QOS", "COMPRESSED_IMAGE_TOPIC", "IMAGE_QOS", "RAW_IMAGE_TOPIC", "REPLY_QOS", "STATIC_QOS",
           "ClockMode", "DriveLimits", "Durability", "History", "QosProfile", "Reliability", "Ros2Options", "Topics",
           "check_domain", "cyclone_xml", "dds_topic", "node_env", "per_run_domain", "topic_problem"]
