"""The ``ros2`` transport, harness side: an unmodified ROS 2 node is the target.

The harness speaks DDS itself (Cyclone DDS, no ROS installation) with ROS 2's
conventions: topics ``rt/<name>``, rmw's type names, CDR. Per frame it publishes, in
this order and all with the frame's stamp (hil.adapters.ros2.answers: stamps and
matching): ``/clock`` (clock ``sim`` only: ``rosgraph_msgs/Clock`` = the frame's sim
time), ``sensor_msgs/CameraInfo``, the ego speed (``geometry_msgs/TwistStamped``,
``twist.linear.x``), and the image (``sensor_msgs/Image`` rgb8/bgr8, or
``CompressedImage`` jpeg). At open it publishes the camera mount once on
``/tf_static`` (transient local): ``base_link`` -> ``camera_link`` (mount position,
yaw then pitch) -> ``camera_optical_frame``. ROS 2 pixel coordinates put a pixel's
centre on the integer (the harness: on +0.5), so ``cx``, ``cy`` and boxes are shifted
by 0.5 px each way.

It reads ``ackermann_msgs/AckermannDriveStamped`` (required) and
``vision_msgs/Detection2DArray`` (optional) and turns each frame's pair into one
ESTIMATE: the control, the derived driving state, the objects; ``t_reply`` is the
DDS source timestamp of the answer's last message (the node's system clock when its
rmw wrote it), ``t_rx`` and ``t_infer_*`` are unknown (None). t0' is stamped when
the reader thread takes the sample.

HELLO. There is none on ROS 2: the link makes one when the node's side is matched
(a subscriber on the image topic, a writer on every answer topic), named after the
control writer's participant (its DDS entity name, else its process), clock
REALTIME. Only the answer writers matched then are accepted for the run; a sample
from any other writer is ignored, counted and named (``ros2_stats``), as is a
writer on an answer topic with another type, and a sample that is not valid CDR
(each also a protocol event, the first per writer). Clock-sync requests have no
ROS 2 counterpart: none is answered (``sync_exchange`` returns None at once).
Instead every answer matched to its frame by stamp is one 4-timestamp sample
(t1 = t_tx, t2 = t3 = its source timestamp, t4 = t0'): the node's system clock
offset, bounded by half the frame's round trip (inference included).

Liveness: the node has gone when nothing subscribes to the image topic any more
and no answer writer is matched (its participant left, or its lease ran out:
``lease_ms`` for a node the harness configures).
"""

from __future__ import annotations

import dataclasses
import queue
import threading
from typing import Any

from hil.adapters.link import Link, ProtocolFault, Received
from hil.adapters.ros2.answers import (CONTROL, DETECTIONS, OPTICAL_Q, AnswerBook, DriveMapping, Sent, camera_info_of,
                                       mount_quaternion, ns_of, objects_of, stamp_of)
from hil.adapters.ros2.cdr import CdrError, decode
from hil.adapters.ros2.dds import Participant, WriterInfo, handle_of, matched_writers, take, write
from hil.adapters.ros2.msgs import (AckermannDriveStamped, CameraInfo, Clock, CompressedImage, Detection2DArray, Header,
                                    Image, TFMessage, Transform, TransformStamped, Twist, TwistStamped, Vector3,
                                    dds_name)
from hil.adapters.ros2.options import CLOCK_QOS, STATIC_QOS, ClockMode, Ros2Options, dds_topic, topic_problem
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import ClockId, Frame, Hello, ImageEncoding, MsgType, SyncResponse
from hil.common.errors import ConfigError, TransportError
from hil.timing.clock import Clock as HarnessClock
from hil.timing.clock import RealtimeClock
from hil.timing.sync import SyncSample

POLL_S = 0.05  # the reader thread's longest wait: discovery and liveness are checked this often
MAX_NAMED = 16  # foreign writers and type mismatches named in the stats (all are counted)


class Ros2Link(Link):
    """Harness side over ROS 2 (module docstring). ``options`` (``Ros2Options``): the
    domain, Cyclone's discovery, the clock mode, the topics (fully qualified ROS 2
    names), the TF frames and camera mount, QoS and the control mapping's constants;
    ``realtime``: the system clock of ``clock: system`` stamps (tests give their own)."""

    transport_name = "ros2"

    def __init__(self, *, vehicle_id: int, clock: HarnessClock, options: Ros2Options | None = None,
                 realtime: HarnessClock | None = None, rx_queue_size: int = 1024,
                 rx_queue: queue.Queue[Received] | None = None) -> None:
        """Raises ConfigError: a bad option (checked here, before anything opens)."""
        super().__init__(vehicle_id=vehicle_id, clock=clock, rx_queue_size=rx_queue_size, rx_queue=rx_queue)
        o = self.options = options or Ros2Options()
        try:
            self.clock_mode = ClockMode(o.clock)
        except ValueError:
            raise ConfigError(f"ros2 clock={o.clock!r}: expected sim or system") from None
        t = o.topics
        for name, topic in (("image_topic", o.image_topic), ("camera_info_topic", t.camera_info),
                            ("control_topic", t.control), ("clock_topic", t.clock),
                            *((("speed_topic", t.speed),) if t.speed else ()),
                            *((("detections_topic", t.detections),) if t.detections else ())):
            if (problem := topic_problem(topic)) is not None:
                raise ConfigError(f"ros2 {name}: expected {problem}")
        self.domain_id, self.compressed, self.mount = o.domain_id, o.compressed, o.mount
        self.config_xml = o.cyclone_xml()
        self.topics = {"image": o.image_topic, "camera_info": t.camera_info, "speed": t.speed,
                       "clock": t.clock, CONTROL: t.control, DETECTIONS: t.detections}
        self.frames = (o.base_frame, o.camera_frame, o.optical_frame)
        self.image_qos, self.reply_qos = o.image_qos, o.reply_qos
        self.mapping = DriveMapping(**dataclasses.asdict(o.drive))
        self._realtime = realtime or RealtimeClock()
        self._rt_offset_ns = 0
        self._book = AnswerBook(vehicle_id=vehicle_id, kinds=(CONTROL, DETECTIONS) if t.detections else (CONTROL,))
        self._book_lock = threading.Lock()
        self._dds: Participant | None = None
        self._w: dict[str, Any] = {}
        self._r: dict[str, Any] = {}
        self._accepted: dict[str, set[int]] = {}
        self._named: set[str] = set()
        self._sync_seq = 0
        self._last_clock_ns = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.ros2_stats: dict[str, Any] = {
            "domain_id": o.domain_id, "clock": self.clock_mode.value, "images_sent": 0, "write_failures": 0,
            "sync_requests_unanswered": 0, "answers": 0, "matched_by_stamp": 0, "matched_by_arrival": 0,
            "unmatched_answers": 0, "clock_samples": 0, "malformed": 0, "foreign_samples": 0,
            "foreign_writers": [], "type_mismatches": [], "writers": {}}
        self.stats.transport = self.ros2_stats

    # -- opening -----------------------------------------------------------------

    def _open(self) -> None:
        self._dds = dds = Participant(domain_id=self.domain_id, config=self.config_xml,
                                      name=f"hil_harness_v{self.vehicle_id}")
        t = self.topics
        self._w["image"] = dds.writer(t["image"], CompressedImage if self.compressed else Image, self.image_qos)
        self._w["camera_info"] = dds.writer(t["camera_info"], CameraInfo, self.image_qos)
        if t["speed"]:
            self._w["speed"] = dds.writer(t["speed"], TwistStamped, self.image_qos)
        if self.clock_mode == ClockMode.SIM:
            self._w["clock"] = dds.writer(t["clock"], Clock, CLOCK_QOS)
        self._w["tf_static"] = dds.writer("/tf_static", TFMessage, STATIC_QOS)
        self._r[CONTROL] = dds.reader(t[CONTROL], AckermannDriveStamped, self.reply_qos)
        if t[DETECTIONS]:
            self._r[DETECTIONS] = dds.reader(t[DETECTIONS], Detection2DArray, self.reply_qos)
        write(self._w["tf_static"], self._tf_static())
        m0 = self.clock.now_ns()
        r = self._realtime.now_ns()
        self._rt_offset_ns = r - (m0 + self.clock.now_ns()) // 2
        self._thread = threading.Thread(target=self._serve, name=f"ros2-v{self.vehicle_id}", daemon=True)
        self._thread.start()

    def _tf_static(self) -> TFMessage:
        fwd, lat, height, pitch, yaw = self.mount
        base, cam, optical = self.frames
        stamp = stamp_of(self._realtime.now_ns())
        return TFMessage([
            TransformStamped(Header(stamp, base), cam,
                             Transform(Vector3(fwd, lat, height), mount_quaternion(pitch, yaw))),
            TransformStamped(Header(stamp, cam), optical, Transform(Vector3(), OPTICAL_Q))])

    def _matched(self) -> bool:
        return bool(self._w["image"].get_matched_subscriptions()) and all(
            r.get_matched_publications() for r in self._r.values())

    def _say_hello(self) -> None:
        """The node's side is matched: accept its answer writers and make its HELLO."""
        assert self._dds is not None
        names = {}
        for kind, reader in self._r.items():
            handles = matched_writers(reader)
            self._accepted[kind] = handles
            names[self.topics[kind]] = [self._dds.writer_name(reader, h) for h in sorted(handles)]
        self.ros2_stats["writers"] = names
        who = next(iter(names[self.topics[CONTROL]]), "ros2 node").split(" of ", 1)[-1]
        name = who.split(" (", 1)[0] if " (" in who else who
        self._dispatch(Hello(name.encode("utf-8")[:protocol.MAX_NAME_LEN].decode("utf-8", "ignore"), protocol.VERSION,
                             ClockId.REALTIME, 1), self.clock.now_ns())

    def _no_hello_reason(self, timeout_s: float) -> str:
        if self.peer_gone_reason:
            return super()._no_hello_reason(timeout_s)
        missing = []
        if self._dds is not None:
            if not self._w["image"].get_matched_subscriptions():
                missing.append(f"a subscriber of {self.topics['image']} "
                               f"({'sensor_msgs/msg/CompressedImage' if self.compressed else 'sensor_msgs/msg/Image'})")
            missing += [f"a writer on {self.topics[k]} ({dds_name(type(self).reply_type(k))})"
                        for k, r in self._r.items() if not r.get_matched_publications()]
        why = "; ".join(self.ros2_stats["type_mismatches"][:2])
        return (f"no ROS 2 node matched on DDS domain {self.domain_id} within {timeout_s:g} s: missing "
                f"{' and '.join(missing) or 'nothing'}" + (f"; {why}" if why else "") +
                ". Is the node running with ROS_DOMAIN_ID=" f"{self.domain_id}, Cyclone DDS on the interface and peers "
                "of target.ros2, and these topics (QoS: the harness asks "
                f"{self.reply_qos.reliability.value} for answers)?")

    @staticmethod
    def reply_type(kind: str) -> type[Any]:
        return AckermannDriveStamped if kind == CONTROL else Detection2DArray

    # -- the reader thread --------------------------------------------------------

    def _serve(self) -> None:
        from cyclonedds.core import GuardCondition, InstanceState, ReadCondition, SampleState, ViewState, WaitSet

        assert self._dds is not None
        ws = WaitSet(self._dds.dp)
        self._wake = GuardCondition(self._dds.dp)
        ws.attach(self._wake)
        for r in self._r.values():
            ws.attach(ReadCondition(r, SampleState.Any | ViewState.Any | InstanceState.Any))
        hello = False
        while not self._stop.is_set():
            ws.wait(int(POLL_S * 1e9))
            if self._stop.is_set():
                return
            try:
                self._check_types()
                if not hello and self._matched():
                    hello = True
                    self._say_hello()
                for kind, reader in self._r.items():
                    for data, info in take(reader):
                        self._on_sample(kind, reader, data, info, self.clock.now_ns())
                if hello and not self._w["image"].get_matched_subscriptions() and not any(
                        r.get_matched_publications() for r in self._r.values()):
                    self._mark_gone(f"the ROS 2 node left DDS domain {self.domain_id} (no subscriber on "
                                    f"{self.topics['image']}, no writer on {self.topics[CONTROL]})")
                    return
            except TransportError as err:
                self._mark_gone(str(err))
                return

    def _check_types(self) -> None:
        """A writer on one of our topics with another type: named once, counted. Only
        writers discovered after this link opened are seen (Cyclone 11.0.1 gives a
        new discovery reader no history of remote writers); one already running is
        missed, and the HELLO timeout still names the type the harness expects."""
        assert self._dds is not None
        ours = {dds_topic(self.topics[k]): dds_name(self.reply_type(k)) for k in self._r}
        for w in self._dds.writers():
            want = ours.get(w.topic)
            if want is not None and w.type_name != want and w.guid not in self._named:
                self._named.add(w.guid)
                self._fault(f"{w.topic} is written as {w.type_name} by {_who(w)}; the harness reads {want}", 0,
                            "type_mismatches")

    def _fault(self, text: str, offset: int, named: str | None = None) -> None:
        self.stats.last_error = text
        if named is not None:
            lst: list[str] = self.ros2_stats[named]
            if len(lst) < MAX_NAMED:
                lst.append(text)
        fault = Received(ProtocolFault(text, offset), self.clock.now_ns(), self.vehicle_id)  # type: ignore[arg-type]
        self._enqueue(self._rx, fault)

    def _on_sample(self, kind: str, reader: Any, data: bytes, info: Any, t_rx: int) -> None:
        st = self.ros2_stats
        handle = handle_of(info.publication_handle)
        accepted = self._accepted.get(kind)
        if accepted is None:
            return  # before HELLO: not yet the run's
        if handle not in accepted:
            st["foreign_samples"] += 1
            key = f"{kind}:{handle}"
            if key not in self._named:
                self._named.add(key)
                assert self._dds is not None
                self._fault(f"sample on {self.topics[kind]} from {self._dds.writer_name(reader, handle)}, "
                            f"a writer not matched when the run started: ignored", 0, "foreign_writers")
            return
        try:
            msg = decode(self.reply_type(kind), data)
        except CdrError as err:
            st["malformed"] += 1
            assert self._dds is not None
            self._fault(f"malformed CDR sample on {self.topics[kind]} from {self._dds.writer_name(reader, handle)}: "
                        f"{err} (byte offset {err.offset})", err.offset)
            return
        st["answers"] += 1
        source_ns = int(info.source_timestamp)
        with self._book_lock:
            sent, exact = self._book.match(kind, ns_of(msg.header.stamp), t_rx)
            st["matched_by_arrival"] = self._book.matched_by_arrival
            st["unmatched_answers"] = self._book.unmatched
            if sent is None:
                return
            if kind == CONTROL:
                sent.control = self.mapping.control_of(msg.drive, sent.ego_speed_mps)
            else:
                sent.objects = objects_of(msg)
            done = self._book.add(sent, kind, t_rx, source_ns)
        if exact:
            st["matched_by_stamp"] += 1
            st["clock_samples"] += 1
            self._sync_seq += 1
            self._enqueue(self._sync_rx, Received(SyncResponse(self.vehicle_id, self._sync_seq, sent.t_tx_ns, source_ns,
                                                               source_ns), t_rx, self.vehicle_id))
        if done is not None:
            self._dispatch(done[0], done[1])

    # -- sending ---------------------------------------------------------------------

    def sync_exchange(self, *, timeout_s: float = 0.5) -> SyncSample | None:
        """No clock-sync exchange exists on ROS 2: None at once (module docstring)."""
        return None

    def _send_bytes(self, data: bytes) -> None:
        kind = data[5] if len(data) >= protocol.HEADER_SIZE else -1
        if kind == MsgType.SYNC_REQUEST:
            self.ros2_stats["sync_requests_unanswered"] += 1
            return
        if kind != MsgType.FRAME:
            return  # BYE, HEARTBEAT, ERROR: nothing on ROS 2 (a node leaves by leaving the domain)
        f = protocol.decode(data)
        assert isinstance(f, Frame)
        self._publish(f)

    def _publish(self, f: Frame) -> None:
        stamp_ns = f.sim_time_ns if self.clock_mode == ClockMode.SIM else f.t0_ns + self._rt_offset_ns
        header = Header(stamp_of(stamp_ns), self.frames[2])
        c = f.camera
        info = camera_info_of(header, f.width, f.height, c.fx, c.fy, c.cx, c.cy)
        if f.encoding == ImageEncoding.JPEG:
            image: Any = CompressedImage(header, "jpeg", f.data)
        else:
            image = Image(header, f.height, f.width, "rgb8" if f.encoding == ImageEncoding.RGB8 else "bgr8", 0,
                          3 * f.width, f.data)
        if (f.encoding == ImageEncoding.JPEG) != self.compressed:
            raise TransportError(f"a {f.encoding.name} frame on a link opened for "
                                 f"{'JPEG' if self.compressed else 'raw'} images")
        with self._book_lock:
            self._book.sent(Sent(f.frame_id, stamp_ns, f.t_tx_ns, f.ego_speed_mps))
        try:
            if "clock" in self._w and stamp_ns > self._last_clock_ns:
                write(self._w["clock"], Clock(header.stamp))
                self._last_clock_ns = stamp_ns
            write(self._w["camera_info"], info)
            if "speed" in self._w:
                write(self._w["speed"], TwistStamped(Header(header.stamp, self.frames[0]),
                                                     Twist(Vector3(f.ego_speed_mps, 0.0, 0.0))))
            write(self._w["image"], image)
        except TransportError as err:
            # A reliable writer that found no room within its blocking time: the frame
            # is lost (it times out as dropped), the run goes on.
            self.ros2_stats["write_failures"] += 1
            self.stats.last_error = str(err)
            return
        self.ros2_stats["images_sent"] += 1

    def _close_transport(self) -> None:
        stop = getattr(self, "_stop", None)
        if stop is not None:
            stop.set()
        wake = getattr(self, "_wake", None)
        if wake is not None:
            wake.set(True)
        thread = getattr(self, "_thread", None)
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        dds, self._dds = getattr(self, "_dds", None), None
        if dds is not None:
            dds.close()


def _who(w: WriterInfo) -> str:
    return f"writer {w.guid} of {w.who}"

