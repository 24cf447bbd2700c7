"""An rclpy node as the harness's target: the OpenCV baseline behind ROS 2 topics, for
users with a ROS 2 installation. NOT RUN HERE: these machines have no ROS 2; the
conventions it follows are those the CI checks with hil.adapters.ros2.target (the same
baseline as a ROS 2 node on Cyclone DDS alone, README "ROS 2").

With ROS 2 Humble (or newer) and ``ros-<distro>-vision-msgs``,
``ros-<distro>-ackermann-msgs``, ``ros-<distro>-rmw-cyclonedds-cpp`` installed, and this
repository's ``hil-target-sdk`` plus OpenCV importable by the ROS Python::

    export RMW_IMPLEMENTATION=rmw_cyclonedds_cpp ROS_DOMAIN_ID=0
    export CYCLONEDDS_URI='<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><Peers><Peer address="127.0.0.1"/></Peers><ParticipantIndex>auto</ParticipantIndex></Discovery></Domain></CycloneDDS>'
    python3 targets/ros2_rclpy_node.py --ros-args -p use_sim_time:=true
    hil run hil_configs/ros2.yaml --set 'target.command=[]' --set target.ros2.domain_id=0

The node subscribes to the compressed image, the camera info and the ego speed (taking
the latest of each), runs the baseline, and publishes the detections and an Ackermann
command under the image's header: what lets the harness match the answer to its frame.
The camera mount (height, pitch) comes from parameters here; a stack would look it up
in /tf_static, where the harness publishes it.
"""

from __future__ import annotations

import math
import sys


def main() -> int:  # pragma: no cover - needs ROS 2
    import rclpy
    from ackermann_msgs.msg import AckermannDriveStamped
    from geometry_msgs.msg import TwistStamped
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, CompressedImage
    from vision_msgs.msg import Detection2D, Detection2DArray, ObjectHypothesisWithPose

    from hil.adapters.wire.messages import CameraInfo as HilCamera
    from hil.adapters.wire.messages import DrivingState, Frame, ImageEncoding
    from hil.targets.cv_baseline import CvBaseline

    class BaselineNode(Node):  # type: ignore[misc]  # rclpy is not installed here: Node is Any
        def __init__(self) -> None:
            super().__init__("cv_baseline")
            self.mount_height = float(self.declare_parameter("mount_height_m", 1.3).value)
            self.pitch = math.radians(float(self.declare_parameter("pitch_deg", 0.0).value))
            self.ai = CvBaseline()
            self.info: CameraInfo | None = None
            self.speed = 0.0
            self.create_subscription(CameraInfo, "/camera/camera_info", self.on_info, 10)
            self.create_subscription(TwistStamped, "/vehicle/twist", self.on_speed, 10)
            self.create_subscription(CompressedImage, "/camera/image_raw/compressed", self.on_image, 2)
            self.control = self.create_publisher(AckermannDriveStamped, "/control/ackermann_cmd", 10)
            self.detections = self.create_publisher(Detection2DArray, "/perception/detections", 10)

        def on_info(self, msg: CameraInfo) -> None:
            self.info = msg

        def on_speed(self, msg: TwistStamped) -> None:
            self.speed = msg.twist.linear.x

        def on_image(self, msg: CompressedImage) -> None:
            if self.info is None:
                return
            k = self.info.k  # ROS pixel centres are on integers; the baseline's on +0.5
            cam = HilCamera(k[0], k[4], k[2] + 0.5, k[5] + 0.5, self.mount_height, self.pitch)
            frame = Frame(0, 0, 0, 0, 0, self.info.width, self.info.height, ImageEncoding.JPEG, cam, self.speed,
                          bytes(msg.data))
            out = self.ai.infer(frame)
            arr = Detection2DArray(header=msg.header)
            for o in out.objects:
                d = Detection2D(header=msg.header)
                x0, y0, x1, y1 = o.box_px
                d.bbox.center.position.x, d.bbox.center.position.y = (x0 + x1) / 2 - 0.5, (y0 + y1) / 2 - 0.5
                d.bbox.size_x, d.bbox.size_y = x1 - x0, y1 - y0
                h = ObjectHypothesisWithPose()
                h.hypothesis.class_id, h.hypothesis.score = o.cls.label, float(o.confidence)
                h.pose.pose.position.x, h.pose.pose.position.y, h.pose.pose.position.z = map(float, o.position_m)
                d.results.append(h)
                arr.detections.append(d)
            self.detections.publish(arr)
            cmd = AckermannDriveStamped(header=msg.header)
            c = out.control
            cmd.drive.steering_angle = float(c.steering_rad)
            cmd.drive.acceleration = float(3.0 * c.throttle - 8.0 * c.brake)  # the harness's car: 3 and 8 m/s^2
            cmd.drive.speed = 0.0 if out.state == DrivingState.STOP else float(self.speed)
            self.control.publish(cmd)

    rclpy.init(args=sys.argv)
    node = BaselineNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":  # pragma: no cover - needs ROS 2
    raise SystemExit(main())
