"""Message types carried on the wire, as frozen dataclasses.

Units: times are integer nanoseconds (``*_ns``; ``*_target_ns`` on the target's
clock), distances metres, angles radians, boxes pixels ``(x0, y0, x1, y1)`` with the
origin at the image's top-left corner. Object positions are in the camera-ground
frame: origin on the road directly under the camera, x forward along the camera's
heading, y left, z up; a rig of two or more cameras has one such frame, under camera
0's mount with the vehicle's axes, for every camera (PROTOCOL.md 4.3).

Byte layouts are in ``PROTOCOL.md``; ``hil.adapters.wire.protocol`` encodes and decodes.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from hil.common.classes import ObjectClass  # the wire's class codes (one list: hil.common.classes)


class MsgType(IntEnum):
    HELLO = 1
    FRAME = 2
    ESTIMATE = 3
    SYNC_REQUEST = 4
    SYNC_RESPONSE = 5
    HEARTBEAT = 6
    ERROR = 7
    BYE = 8
    COMMAND = 9
    AUTH = 10


class DrivingState(IntEnum):
    SAFE = 0
    SLOW = 1
    STOP = 2


class ImageEncoding(IntEnum):
    RGB8 = 0
    BGR8 = 1
    JPEG = 2


class ClockId(IntEnum):
    """Which clock a target stamps with."""

    MONOTONIC = 0
    REALTIME = 1
    PTP = 2
    DEVICE = 3


@dataclass(frozen=True)
class CameraInfo:
    """Calibration sent with every frame: pinhole intrinsics (pixels), the camera's
    mount height above the road (m) and its pitch (rad, positive looks down)."""

    fx: float
    fy: float
    cx: float
    cy: float
    mount_height_m: float
    pitch_rad: float = 0.0


@dataclass(frozen=True)
class Hello:
    """First message of a target: who it is and how it keeps time."""

    target_name: str
    protocol_version: int
    clock_id: ClockId
    clock_resolution_ns: int
    capabilities: int = 0


@dataclass(frozen=True)
class Frame:
    """One camera image, stamped by the harness.

    ``camera_index`` is the camera of the vehicle's rig it came from (0: the first or
    only camera) and ``camera_count`` the cameras of its frame set, the images of one
    capture instant (0: a single camera, not a set; PROTOCOL.md 4.2). ``t0_ns`` is the capture instant (render finished) and ``t_tx_ns`` the hand-off
    to the transport, both on the harness clock; ``sim_time_ns`` is the simulated
    instant the image shows. ``ego_speed_mps`` is the vehicle's own speed signal
    (as a wheel-speed sensor would report it).
    """

    vehicle_id: int
    frame_id: int
    sim_time_ns: int
    t0_ns: int
    t_tx_ns: int
    width: int
    height: int
    encoding: ImageEncoding
    camera: CameraInfo
    ego_speed_mps: float
    data: bytes
    camera_index: int = 0
    camera_count: int = 0

    @property
    def set_id(self) -> int:
        """The frame set this frame belongs to (PROTOCOL.md 4.2): the ``frame_id`` of its
        set's camera 0, which a fusing target's ESTIMATE answers; a single camera's frame
        (``camera_count`` 0) is a set of its own, ``frame_id``."""
        return self.frame_id - self.camera_index


@dataclass(frozen=True)
class DetectedObject:
    """An object the AI believes it sees. ``position_m`` is the centre of its nearest
    visible face at road level, in the camera-ground frame (see module docstring)."""

    cls: ObjectClass
    confidence: float
    box_px: tuple[float, float, float, float]
    position_m: tuple[float, float, float]
    camera: int = 0  # the camera whose image ``box_px`` is in (a fusing target's estimate of a frame set)


@dataclass(frozen=True)
class Control:
    """Actuation request: steering angle (rad, positive turns left), throttle and
    brake in [0, 1]."""

    steering_rad: float = 0.0
    throttle: float = 0.0
    brake: float = 0.0


@dataclass(frozen=True)
class Inference:
    """What an AI's ``infer(frame)`` returns; the SDK adds the timestamps."""

    state: DrivingState
    control: Control
    objects: tuple[DetectedObject, ...] = ()


@dataclass(frozen=True)
class Estimate:
    """The target's answer to one frame, stamped on the target's own clock.

    A stamp is ``None`` where the target cannot give it (a ROS 2 node reached over
    the ``ros2`` transport has no receipt or inference stamps: PROTOCOL.md targets
    always give all four); the stages that need it are then unknown, never zero.
    """

    vehicle_id: int
    frame_id: int
    state: DrivingState
    control: Control
    objects: tuple[DetectedObject, ...]
    t_rx_target_ns: int | None
    t_infer_start_target_ns: int | None
    t_infer_end_target_ns: int | None
    t_reply_target_ns: int | None


@dataclass(frozen=True)
class SyncRequest:
    """Clock-sync probe: ``t1_ns`` is the harness send time."""

    vehicle_id: int
    seq: int
    t1_ns: int


@dataclass(frozen=True)
class SyncResponse:
    """Clock-sync reply: the echoed ``t1_ns`` with the target's receive (``t2``) and
    send (``t3``) times on its own clock."""

    vehicle_id: int
    seq: int
    t1_ns: int
    t2_target_ns: int
    t3_target_ns: int


@dataclass(frozen=True)
class Heartbeat:
    vehicle_id: int
    t_sender_ns: int


@dataclass(frozen=True)
class ErrorMsg:
    """A peer reports a problem (for example a message it could not decode)."""

    vehicle_id: int
    code: int
    message: str


@dataclass(frozen=True)
class Bye:
    """Orderly end of a session."""

    vehicle_id: int
    reason: str = ""


@dataclass(frozen=True)
class Command:
    """A line of text for the control software of a target (harness -> target, e.g.
    ``"swap detector cv"``), or the target's reply to it (target -> harness, same
    ``seq``). Sent only to a target whose HELLO announced ``CAP_COMMANDS``
    (``hil.adapters.wire.protocol``). ``t_sender_ns``: the sender's clock at send."""

    vehicle_id: int
    seq: int
    text: str
    t_sender_ns: int = 0


class AuthStep(IntEnum):
    CHALLENGE = 1  # harness -> target: 32 random bytes
    PROOF = 2  # target -> harness: HMAC-SHA256 of the challenge under the shared token


@dataclass(frozen=True)
class Auth:
    """The target proves it holds the run's token (PROTOCOL.md section 4.8): the
    harness sends a CHALLENGE (32 random bytes) only to a target whose HELLO announced
    ``CAP_AUTH``; the target answers with the PROOF, ``hil.adapters.wire.auth.proof``."""

    vehicle_id: int
    step: AuthStep
    data: bytes  # 32 bytes: the challenge, or the proof


Message = Hello | Frame | Estimate | SyncRequest | SyncResponse | Heartbeat | ErrorMsg | Bye | Command | Auth

__all__ = [
    "Auth", "AuthStep", "Bye", "CameraInfo", "ClockId", "Command", "Control", "DetectedObject", "DrivingState",
    "ErrorMsg", "Estimate", "Frame", "Heartbeat", "Hello", "ImageEncoding",
    "Inference", "Message", "MsgType", "ObjectClass", "SyncRequest", "SyncResponse",
]
