"""The ROS 2 messages the ``ros2`` transport speaks, as Cyclone DDS types.

Each class is an ``IdlStruct`` named as ROS 2's rmw layer names it on the wire
(``sensor_msgs/msg/Image`` is the DDS type ``sensor_msgs::msg::dds_::Image_``) with
the fields of the ROS 2 Humble definition, in order; so a node using
``rmw_cyclonedds_cpp`` matches our readers and writers by type name, and the CDR
bytes are ROS 2's (checked against ``rosbags``' serializer, store ROS2_HUMBLE, in
tests/adapters/ros2/test_msgs.py). ``vision_msgs`` (4.1.1, Humble's) and
``ackermann_msgs`` (2.0.2) are not in ``rosbags``; their field lists are in
``msg/`` (beside this module) as ``.msg`` files (:func:`msg_definitions`), from which the tests
register them.

``uint8[]`` fields (image data) hold ``bytes`` (hil.adapters.ros2.cdr encodes them
in one copy).

Not ``from __future__ import annotations``: Cyclone reads the field annotations as
objects.
"""

from dataclasses import dataclass, field
from importlib import resources

try:
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import types as t
except ImportError as _err:  # pragma: no cover - depends on the install
    raise ImportError("the ros2 transport needs Cyclone DDS: pip install cyclonedds==11.0.1") from _err

# ruff: noqa: N815 - field names are ROS 2's


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str = ""


@dataclass
class Clock(IdlStruct, typename="rosgraph_msgs::msg::dds_::Clock_"):
    clock: Time = field(default_factory=Time)


@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header = field(default_factory=Header)
    height: t.uint32 = 0
    width: t.uint32 = 0
    encoding: str = ""
    is_bigendian: t.uint8 = 0
    step: t.uint32 = 0
    data: t.sequence[t.uint8] = b""


@dataclass
class CompressedImage(IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
    header: Header = field(default_factory=Header)
    format: str = ""
    data: t.sequence[t.uint8] = b""


@dataclass
class RegionOfInterest(IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: t.uint32 = 0
    y_offset: t.uint32 = 0
    height: t.uint32 = 0
    width: t.uint32 = 0
    do_rectify: bool = False


@dataclass
class CameraInfo(IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    header: Header = field(default_factory=Header)
    height: t.uint32 = 0
    width: t.uint32 = 0
    distortion_model: str = ""
    d: t.sequence[t.float64] = field(default_factory=list)
    k: t.array[t.float64, 9] = field(default_factory=lambda: [0.0] * 9)
    r: t.array[t.float64, 9] = field(default_factory=lambda: [0.0] * 9)
    p: t.array[t.float64, 12] = field(default_factory=lambda: [0.0] * 12)
    binning_x: t.uint32 = 0
    binning_y: t.uint32 = 0
    roi: RegionOfInterest = field(default_factory=RegionOfInterest)


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose = field(default_factory=Pose)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TwistStamped_"):
    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped] = field(default_factory=list)


@dataclass
class Point2D(IdlStruct, typename="vision_msgs::msg::dds_::Point2D_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0


@dataclass
class Pose2D(IdlStruct, typename="vision_msgs::msg::dds_::Pose2D_"):
    position: Point2D = field(default_factory=Point2D)
    theta: t.float64 = 0.0


@dataclass
class BoundingBox2D(IdlStruct, typename="vision_msgs::msg::dds_::BoundingBox2D_"):
    center: Pose2D = field(default_factory=Pose2D)
    size_x: t.float64 = 0.0
    size_y: t.float64 = 0.0


@dataclass
class ObjectHypothesis(IdlStruct, typename="vision_msgs::msg::dds_::ObjectHypothesis_"):
    class_id: str = ""
    score: t.float64 = 0.0


@dataclass
class ObjectHypothesisWithPose(IdlStruct, typename="vision_msgs::msg::dds_::ObjectHypothesisWithPose_"):
    hypothesis: ObjectHypothesis = field(default_factory=ObjectHypothesis)
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)


@dataclass
class Detection2D(IdlStruct, typename="vision_msgs::msg::dds_::Detection2D_"):
    header: Header = field(default_factory=Header)
    results: t.sequence[ObjectHypothesisWithPose] = field(default_factory=list)
    bbox: BoundingBox2D = field(default_factory=BoundingBox2D)
    id: str = ""


@dataclass
class Detection2DArray(IdlStruct, typename="vision_msgs::msg::dds_::Detection2DArray_"):
    header: Header = field(default_factory=Header)
    detections: t.sequence[Detection2D] = field(default_factory=list)


@dataclass
class AckermannDrive(IdlStruct, typename="ackermann_msgs::msg::dds_::AckermannDrive_"):
    steering_angle: t.float32 = 0.0
    steering_angle_velocity: t.float32 = 0.0
    speed: t.float32 = 0.0
    acceleration: t.float32 = 0.0
    jerk: t.float32 = 0.0


@dataclass
class AckermannDriveStamped(IdlStruct, typename="ackermann_msgs::msg::dds_::AckermannDriveStamped_"):
    header: Header = field(default_factory=Header)
    drive: AckermannDrive = field(default_factory=AckermannDrive)


ALL: tuple[type[IdlStruct], ...] = (
    Time, Header, String, Clock, Image, CompressedImage, RegionOfInterest, CameraInfo, Vector3, Point, Quaternion,
    Pose, PoseWithCovariance, Twist, TwistStamped, Transform, TransformStamped, TFMessage, Point2D, Pose2D,
    BoundingBox2D, ObjectHypothesis, ObjectHypothesisWithPose, Detection2D, Detection2DArray, AckermannDrive,
    AckermannDriveStamped,
)

# The packages whose definitions ship in msg/ (rosbags' ROS2_HUMBLE store lacks them).
SHIPPED_PACKAGES = ("vision_msgs", "ackermann_msgs")


def ros_name(cls: type[IdlStruct]) -> str:
    """ROS 2's name of a message type: ``sensor_msgs/msg/Image`` for ``Image``."""
    pkg, sub, _dds, name = dds_name(cls).split("::")
    return f"{pkg}/{sub}/{name.removesuffix('_')}"


def dds_name(cls: type[IdlStruct]) -> str:
    """The DDS type name rmw gives it: ``sensor_msgs::msg::dds_::Image_``."""
    return str(cls.__idl_typename__)


def msg_definitions() -> dict[str, str]:
    """The shipped ``.msg`` definitions, ``{"vision_msgs/msg/Detection2D": text}``."""
    out: dict[str, str] = {}
    root = resources.files("hil.adapters.ros2").joinpath("msg")
    for pkg in SHIPPED_PACKAGES:
        for entry in root.joinpath(pkg, "msg").iterdir():
            if entry.name.endswith(".msg"):
                out[f"{pkg}/msg/{entry.name.removesuffix('.msg')}"] = entry.read_text(encoding="utf-8")
    return out


__all__ = ["ALL", "SHIPPED_PACKAGES", "dds_name", "msg_definitions", "ros_name",
           *(c.__name__ for c in ALL)]
