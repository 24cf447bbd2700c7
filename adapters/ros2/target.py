"""The ``ros2`` transport, target side: any SDK target (``serve(infer, transport="ros2")``,
``python -m hil.targets.cv_baseline --transport ros2``) runs as a ROS 2 node built on
Cyclone DDS, with ROS 2's conventions and nothing of the harness's protocol on the
wire, so it and an unmodified ROS 2 stack are interchangeable under the harness.

It subscribes to ``sensor_msgs/Image`` on ``image`` and ``CompressedImage`` on
``compressed_image``, to ``CameraInfo``, the ego speed (``TwistStamped``) and
``/tf_static`` (the camera mount: the transform to the images' frame and the one to
its parent give the mount height and pitch); each image becomes a frame for the SDK
endpoint, with the camera info and speed of the same stamp (else the latest). An
image that comes before any camera info or mount waits for them (the newest
``HELD`` images; an older one is skipped, counted): the transient-local
``/tf_static`` reaches a node that joined late through the reliable protocol's
repair, which can come after the first images. Each estimate goes out as
a ``Detection2DArray`` and an ``AckermannDriveStamped`` (hil.adapters.ros2.answers),
both under the image's header, as ROS 2 perception copies it.

Where it runs: ``ROS_DOMAIN_ID`` and ``CYCLONEDDS_URI`` (as a ROS 2 node reads them;
without the latter, loopback only) unless given; topics as ``DEFAULT_TOPICS``, or as
the harness that started it says in ``HIL_ROS2_TOPICS`` (JSON), as a launch file
remaps a node's. It serves until the harness leaves the domain (its image writers are
gone), SIGTERM or Ctrl-C; with ``keep_serving`` it then waits for the next harness.
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
from collections import OrderedDict, deque
from collections.abc import Mapping
from typing import Any

from hil.adapters.ros2.answers import PIXEL_CENTRE, DriveMapping, detections_of, ns_of
from hil.adapters.ros2.cdr import CdrError, decode
from hil.adapters.ros2.dds import Participant, take, write
from hil.adapters.ros2.msgs import (AckermannDriveStamped, CameraInfo, CompressedImage, Detection2DArray, Header, Image,
                                    TFMessage, TwistStamped)
from hil.adapters.ros2.options import (COMPRESSED_IMAGE_TOPIC, IMAGE_QOS, RAW_IMAGE_TOPIC, REPLY_QOS, STATIC_QOS,
                                       Topics, cyclone_xml, topic_problem)
from hil.adapters.sdk import Endpoint, announce_line, serving
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import CameraInfo as HilCameraInfo
from hil.adapters.wire.messages import Estimate, Frame, ImageEncoding, MsgType
from hil.common.errors import ConfigError, TransportError

_HARNESS = Topics()  # the harness's defaults (a node the harness starts is told its run's anyway)
DEFAULT_TOPICS: Mapping[str, str] = {
    "image": RAW_IMAGE_TOPIC, "compressed_image": COMPRESSED_IMAGE_TOPIC, "camera_info": _HARNESS.camera_info,
    "speed": _HARNESS.speed, "control": _HARNESS.control, "detections": _HARNESS.detections}
POLL_S = 0.05
_KEPT = 64  # camera infos and speeds kept by stamp
HELD = 2  # images waiting for their camera info or mount (IMAGE_QOS's depth: a slow node's newest)


class Ros2Node:
    """One node's DDS side for ``ep`` (used by ``serve_endpoint``)."""

    def __init__(self, ep: Endpoint, *, dds: Participant, topics: Mapping[str, str], vehicle_id: int,
                 mapping: DriveMapping) -> None:
        self.ep, self.dds, self.topics, self.vehicle_id, self.mapping = ep, dds, topics, vehicle_id, mapping
        # Polled in this order: what an image needs comes first.
        self.readers = {"tf_static": dds.reader("/tf_static", TFMessage, STATIC_QOS),
                        "camera_info": dds.reader(topics["camera_info"], CameraInfo, IMAGE_QOS)}
        if topics.get("speed"):
            self.readers["speed"] = dds.reader(topics["speed"], TwistStamped, IMAGE_QOS)
        self.readers["image"] = dds.reader(topics["image"], Image, IMAGE_QOS)
        self.readers["compressed_image"] = dds.reader(topics["compressed_image"], CompressedImage, IMAGE_QOS)
        self.control = dds.writer(topics["control"], AckermannDriveStamped, REPLY_QOS)
        self.detections = dds.writer(topics["detections"], Detection2DArray, REPLY_QOS) \
            if topics.get("detections") else None
        self._infos: OrderedDict[int, CameraInfo] = OrderedDict()
        self._speeds: OrderedDict[int, float] = OrderedDict()
        self._transforms: dict[str, tuple[str, Any]] = {}  # child frame -> (parent, Transform)
        self._frames: OrderedDict[int, tuple[Header, float]] = OrderedDict()
        self._waiting: deque[tuple[Any, bool, int]] = deque()  # (image, compressed, t_rx), oldest first
        self._lock = threading.Lock()
        self._next_id = 0
        self.skipped: dict[str, int] = {}
        self.malformed = 0

    def harness_present(self) -> bool:
        return bool(self.readers["image"].get_matched_publications()
                    or self.readers["compressed_image"].get_matched_publications())

    def poll(self) -> None:
        """Take what came and hand the images to the endpoint."""
        for kind, reader in self.readers.items():
            for data, _info in take(reader):
                t_rx = self.ep.clock.now_ns()
                try:
                    msg = decode(_TYPES[kind], data)
                except CdrError as err:
                    self.malformed += 1
                    print(f"ros2 target: malformed sample on {self.topics.get(kind, kind)}: {err} "
                          f"(byte offset {err.offset})", file=sys.stderr, flush=True)
                    continue
                self._on(kind, msg, t_rx)

    def _on(self, kind: str, msg: Any, t_rx: int) -> None:
        if kind == "tf_static":
            for tr in msg.transforms:
                self._transforms[tr.child_frame_id] = (tr.header.frame_id, tr.transform)
        elif kind == "camera_info":
            _keep(self._infos, ns_of(msg.header.stamp), msg)
        elif kind == "speed":
            _keep(self._speeds, ns_of(msg.header.stamp), float(msg.twist.linear.x))
        else:
            if len(self._waiting) == HELD:
                old = self._waiting.popleft()[0]
                self._skip(self._missing(old) or "")
            self._waiting.append((msg, kind == "compressed_image", t_rx))
        self._release()

    def _release(self) -> None:
        """Hand on the images waiting, oldest first, once what they need has come;
        each keeps its own arrival."""
        while self._waiting:
            img, compressed, t_rx = self._waiting[0]
            mount = self._mount(img.header.frame_id) if self._infos else None
            if mount is None:  # ``_missing`` says which
                return
            self._waiting.popleft()
            frame = self._frame(img, compressed=compressed, mount=mount)
            if frame is not None:
                self.ep.on_message(frame, t_rx)

    def _missing(self, img: Any) -> str | None:
        """What the image still needs before it is a frame (None: nothing)."""
        if not self._infos:
            return "no camera info yet"
        if self._mount(img.header.frame_id) is None:
            return f"no /tf_static mount of {img.header.frame_id!r}"
        return None

    def _skip(self, why: str) -> None:
        if why not in self.skipped:
            print(f"ros2 target: skipping images: {why}", file=sys.stderr, flush=True)
        self.skipped[why] = self.skipped.get(why, 0) + 1

    def _mount(self, optical: str) -> tuple[float, float] | None:
        """(mount height m, pitch rad) from the transform chain base -> camera -> optical."""
        link = self._transforms.get(optical)
        mount = self._transforms.get(link[0]) if link is not None else None
        if mount is None:
            return None
        q = mount[1].rotation
        # pitch of yaw-then-pitch: the forward axis's drop below the horizontal
        sin_p = 2 * (q.w * q.y - q.z * q.x)
        return float(mount[1].translation.z), math.asin(max(-1.0, min(1.0, sin_p)))

    def _frame(self, img: Any, *, compressed: bool, mount: tuple[float, float]) -> Frame | None:
        """``img`` as a frame, once its mount and a camera info are in (``_release``)."""
        stamp = ns_of(img.header.stamp)
        info = self._infos.get(stamp) or next(reversed(self._infos.values()))
        if compressed:
            if not any(f in img.format.lower() for f in ("jpeg", "jpg", "png")):
                self._skip(f"compressed format {img.format!r} (jpeg or png expected)")
                return None
            encoding, width, height = ImageEncoding.JPEG, int(info.width), int(info.height)
        elif img.encoding in ("rgb8", "bgr8") and img.step == 3 * img.width:
            encoding = ImageEncoding.RGB8 if img.encoding == "rgb8" else ImageEncoding.BGR8
            width, height = int(img.width), int(img.height)
        else:
            self._skip(f"image encoding {img.encoding!r} with step {img.step} (rgb8 or bgr8, unpadded, expected)")
            return None
        speed = self._speeds.get(stamp, next(reversed(self._speeds.values())) if self._speeds else 0.0)
        k = info.k
        camera = HilCameraInfo(k[0], k[4], k[2] + PIXEL_CENTRE, k[5] + PIXEL_CENTRE, mount[0], mount[1])
        with self._lock:
            fid, self._next_id = self._next_id, self._next_id + 1
            _keep(self._frames, fid, (img.header, speed))
        return Frame(self.vehicle_id, fid, stamp, stamp, stamp, width, height, encoding, camera, speed, bytes(img.data))

    def send(self, data: bytes) -> None:
        """The endpoint's messages: an ESTIMATE goes out as ROS 2 messages; the rest
        (HELLO, ERROR, BYE) has no ROS 2 form."""
        if len(data) < protocol.HEADER_SIZE or data[5] != MsgType.ESTIMATE:
            return
        est = protocol.decode(data)
        assert isinstance(est, Estimate)
        with self._lock:
            got = self._frames.pop(est.frame_id, None)
        if got is None:
            return
        header, speed = got
        if self.detections is not None:
            write(self.detections, detections_of(est.objects, header))
        write(self.control, AckermannDriveStamped(header, self.mapping.drive_of(est.control, est.state, speed)))


_TYPES: Mapping[str, type[Any]] = {"image": Image, "compressed_image": CompressedImage, "camera_info": CameraInfo,
                                   "tf_static": TFMessage, "speed": TwistStamped}


def _keep(d: OrderedDict[int, Any], key: int, value: Any) -> None:
    d[key] = value
    while len(d) > _KEPT:
        d.popitem(last=False)


def node_topics(topics: Mapping[str, str] | None = None) -> dict[str, str]:
    """``DEFAULT_TOPICS``, then ``HIL_ROS2_TOPICS`` (JSON), then ``topics``.

    Raises:
        ConfigError: ``HIL_ROS2_TOPICS`` is not a JSON object of strings, or names an unknown topic.
    """
    out = dict(DEFAULT_TOPICS)
    raw = os.environ.get("HIL_ROS2_TOPICS")
    layers: list[Mapping[str, Any]] = []
    if raw:
        try:
            layers.append(json.loads(raw))
        except ValueError as err:
            raise ConfigError(f"HIL_ROS2_TOPICS is not JSON: {err}") from err
    layers.append(topics or {})
    for layer in layers:
        if not isinstance(layer, Mapping) or not all(isinstance(v, str) for v in layer.values()):
            raise ConfigError("ros2 topics: expected an object of topic names, e.g. {\"image\": \"/cam/image_raw\"}")
        unknown = sorted(set(layer) - set(DEFAULT_TOPICS))
        if unknown:
            raise ConfigError(f"ros2 topics: unknown {unknown}; valid: {', '.join(DEFAULT_TOPICS)}")
        out.update(layer)
    for role, name in out.items():
        if name and (problem := topic_problem(name)) is not None:
            raise ConfigError(f"ros2 topic {role}: expected {problem}")
    return out


def serve_endpoint(ep: Endpoint, *, vehicle_id: int = 0, domain_id: int | None = None,
                   cyclone_config: str | None = None, topics: Mapping[str, str] | None = None,
                   keep_serving: bool = False, mapping: DriveMapping | None = None) -> None:
    """Serve ``ep`` as a ROS 2 node (module docstring) until the harness leaves (or,
    with ``keep_serving``, until SIGTERM or ``ep.stop()``).

    Raises:
        TransportError: a bad ``ROS_DOMAIN_ID``, topic name or ``HIL_ROS2_TOPICS`` (one
            line), or Cyclone DDS refused the participant or an endpoint.
    """
    try:
        if domain_id is None:
            raw = os.environ.get("ROS_DOMAIN_ID", "0") or "0"
            if not raw.isdigit():
                raise ConfigError(f"ROS_DOMAIN_ID={raw!r}: expected an integer in 0..232")
            domain_id = int(raw)
        names = node_topics(topics)
        config = cyclone_config or os.environ.get("CYCLONEDDS_URI") or cyclone_xml()
        dds = Participant(domain_id=domain_id, config=config, name=ep.target_name)
    except ConfigError as err:  # the target programs report a TransportError in one line
        raise TransportError(str(err)) from err
    from cyclonedds.core import GuardCondition, InstanceState, ReadCondition, SampleState, ViewState, WaitSet

    gone = threading.Event()
    say = print_line
    where = (f"on DDS domain {domain_id}, vehicle {vehicle_id}, image {names.get('image')} / "
             f"{names.get('compressed_image')}, control {names.get('control')}")
    access = ("the DDS domain: any participant on it can act as the harness (see README, threat model); "
              + ("Cyclone as CYCLONEDDS_URI says" if (cyclone_config or os.environ.get("CYCLONEDDS_URI"))
                 else "loopback discovery, no multicast"))
    sessions = 0
    with dds:
        node = Ros2Node(ep, dds=dds, topics=names, vehicle_id=vehicle_id, mapping=mapping or DriveMapping())
        ws, wake = WaitSet(dds.dp), GuardCondition(dds.dp)
        ws.attach(wake)
        for reader in node.readers.values():  # wakes as a sample arrives, not at the next poll
            ws.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))
        with serving(ep, harness_gone=gone, on_term=lambda: wake.set(True)):
            say(announce_line(ep, transport="ros2", where=where, access=access, keep_serving=keep_serving))
            ep.start(node.send)
            seen = False
            while not ep.stopped:
                ws.wait(int(POLL_S * 1e9))
                node.poll()
                present = node.harness_present()
                if seen and not present:
                    sessions += 1
                    st = ep.stats
                    say(f"{ep.target_name}: harness {sessions} left the domain; {st.frames_received} frames, "
                        f"{st.estimates_sent} estimates so far")
                    if not keep_serving:
                        gone.set()
                        break
                seen = present


def print_line(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


__all__ = ["DEFAULT_TOPICS", "Ros2Node", "node_topics", "serve_endpoint"]
