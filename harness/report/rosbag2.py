"""A run (or a window of it) as a ROS 2 bag that ``ros2 bag play`` feeds into a stack.

``export`` reads ``run.mcap`` (or a corner case's window file) and writes a rosbag2
folder: ``<out>/<out.name>_0.mcap`` in rosbag2's MCAP encoding (profile ``ros2``,
``ros2msg`` schemas with every dependency, CDR messages, each channel's
``offered_qos_profiles``) and ``<out>/metadata.yaml`` (rosbag2 version 5, what ROS 2
Humble reads; newer releases read it too). It is written beside ``run.mcap`` after
the run, as the corner-case windows are, so the recording on the run's hot path and
every reader of ``run.mcap`` stay as they were.

Topics, per vehicle ``V`` (messages: hil.adapters.ros2.msgs, same bytes as the ros2
transport's): ``/V/camera/image_raw/compressed`` (``CompressedImage``, jpeg runs) or
``/V/camera/image_raw`` (``Image``), ``/V/camera/camera_info``, ``/V/vehicle/twist``
(the true ego speed), ``/V/control`` (``AckermannDriveStamped``), ``/V/detections``
(``Detection2DArray``) and ``/V/driving_state`` (``std_msgs/String``: SAFE, SLOW,
STOP); shared: ``/tf`` (``world`` -> every entity, at each ground-truth instant) and
``/tf_static`` (``V`` -> ``V/camera_link`` -> ``V/camera_optical_frame``, transient
local). Estimates map as the ros2 transport reads them (hil.adapters.ros2.answers).

Times, all on the run's wall-clock timeline (the recorder's ``time_anchor``):
``header.stamp`` is the instant the data shows, the exposure instant t_state of the
frame's sim time (an estimate carries its image's header, as ROS 2 perception does;
``/tf`` and the speed that of their ground-truth instant); ``publish_time`` is the
capture time t0 (of the frame; ground truth: its stamp); ``log_time`` is when the
harness had it (t0 for images, t0' for estimates), which ``ros2 bag play`` paces by.
"""

from __future__ import annotations

import argparse
import base64
import bisect
import json
import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from hil.adapters.ros2 import cdr as ros2_cdr
from hil.adapters.ros2.answers import OPTICAL_Q, DriveMapping, camera_info_of, detections_of, mount_quaternion, stamp_of
from hil.adapters.ros2.msgs import (AckermannDriveStamped, CompressedImage, Header, Image, Quaternion, String,
                                    TFMessage, Transform, TransformStamped, Twist, TwistStamped, Vector3,
                                    msg_definitions, ros_name)
from hil.adapters.wire.messages import Control, DetectedObject, DrivingState, ObjectClass
from hil.common.errors import ConfigError
from hil.harness.record.recorder import iter_salvaged_messages

VERSION = 5  # rosbag2 metadata version (ROS 2 Humble's)
ROS_DISTRO = "humble"  # the release the message definitions are pinned to
_FOREVER = {"sec": 2147483647, "nsec": 4294967295}


def qos_yaml(*, transient_local: bool = False, depth: int = 10) -> str:
    """``offered_qos_profiles`` as rosbag2 (metadata version <= 8) writes it: reliable,
    keep last ``depth``, volatile or transient local."""
    return yaml.safe_dump([{"history": 1, "depth": depth, "reliability": 1, "durability": 1 if transient_local else 2,
                            "deadline": dict(_FOREVER), "lifespan": dict(_FOREVER), "liveliness": 1,
                            "liveliness_lease_duration": dict(_FOREVER), "avoid_ros_namespace_conventions": False}],
                          sort_keys=False).strip()


@dataclass
class Bag:
    """What ``export`` wrote: the folder, its MCAP file, messages per topic, and the
    time span (ns since the Unix epoch)."""

    path: Path
    mcap: Path
    counts: dict[str, int] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0

    def to_json(self) -> dict[str, Any]:
        return {"path": str(self.path), "mcap": self.mcap.name, "messages": sum(self.counts.values()),
                "topics": dict(sorted(self.counts.items())), "start_ns": self.start_ns, "end_ns": self.end_ns}


class _Writer:
    """rosbag2's MCAP writer: schemas, channels with QoS, messages, the metadata."""

    def __init__(self, out: Path) -> None:
        from mcap.writer import CompressionType, Writer
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        for name, text in msg_definitions().items():
            self.ts.register(get_types_from_msg(text, name))
        self.bag = Bag(out, out / f"{out.name}_0.mcap")
        self._file = open(self.bag.mcap, "xb")  # noqa: SIM115 - closed in finish()
        self.w = Writer(self._file, compression=CompressionType.ZSTD)
        self.w.start(profile="ros2", library="hil rosbag2 export")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str, str]] = {}  # topic -> (id, type, qos)
        self._seq: dict[str, int] = defaultdict(int)

    def write(self, topic: str, msg: Any, *, log_ns: int, pub_ns: int, transient_local: bool = False) -> None:
        typ = ros_name(type(msg))
        ch = self._channels.get(topic)
        if ch is None:
            if typ not in self._schemas:
                text = self.ts.generate_msgdef(typ, ros_version=2)[0]
                self._schemas[typ] = self.w.register_schema(typ, "ros2msg", text.encode())
            qos = qos_yaml(transient_local=transient_local, depth=1 if transient_local else 10)
            cid = self.w.register_channel(topic, "cdr", self._schemas[typ], {"offered_qos_profiles": qos})
            ch = self._channels[topic] = (cid, typ, qos)
        self._seq[topic] += 1
        self.w.add_message(ch[0], log_time=log_ns, data=ros2_cdr.encode(msg), publish_time=pub_ns,
                           sequence=self._seq[topic])
        b = self.bag
        b.counts[topic] = b.counts.get(topic, 0) + 1
        b.start_ns = log_ns if not b.start_ns else min(b.start_ns, log_ns)
        b.end_ns = max(b.end_ns, log_ns)

    def finish(self) -> Bag:
        b = self.bag
        meta = {"rosbag2_bagfile_information": {
            "version": VERSION, "storage_identifier": "mcap", "relative_file_paths": [b.mcap.name],
            "duration": {"nanoseconds": b.end_ns - b.start_ns},
            "starting_time": {"nanoseconds_since_epoch": b.start_ns},
            "message_count": sum(b.counts.values()),
            "topics_with_message_count": [
                {"topic_metadata": {"name": t, "type": typ, "serialization_format": "cdr", "offered_qos_profiles": qos},
                 "message_count": b.counts[t]} for t, (_id, typ, qos) in self._channels.items()],
            "compression_format": "", "compression_mode": "",
            "files": [{"path": b.mcap.name, "starting_time": {"nanoseconds_since_epoch": b.start_ns},
                       "duration": {"nanoseconds": b.end_ns - b.start_ns}, "message_count": sum(b.counts.values())}]}}
        text = yaml.safe_dump(meta, sort_keys=False)
        self.w.add_metadata("rosbag2", {"serialized_metadata": text, "ROS_DISTRO": ROS_DISTRO})
        self.w.finish()
        self._file.close()
        (b.path / "metadata.yaml").write_text(text)
        return b

    def abort(self) -> None:
        if not self._file.closed:
            self._file.close()


@dataclass
class _Frame:
    frame_id: int
    sim_ns: int
    t0_ns: int
    t_state_ns: int | None


class _Run:
    """What the first pass learns: frames by capture time and id, exposure instants
    by sim time, the egos' true speeds, the camera, the wall-clock offset."""

    def __init__(self, mcap: Path) -> None:
        from mcap.reader import make_reader

        self.offset_ns = 0
        self.camera: dict[str, Any] = {}
        with open(mcap, "rb") as f:
            try:
                for rec in make_reader(f).iter_metadata():
                    if rec.name == "time_anchor":
                        self.offset_ns = int(rec.metadata.get("log_time_offset_ns", "0"))
                    elif rec.name == "config":
                        self.camera = json.loads(rec.metadata.get("yaml_json", "{}")).get("camera", {})
            except Exception:  # noqa: BLE001 - a truncated file has no summary: defaults below
                pass
        self.by_t0: dict[tuple[str, int], _Frame] = {}
        self.by_id: dict[tuple[str, int], _Frame] = {}
        states: dict[int, int] = {}
        self.speed: dict[tuple[str, int], float] = {}
        for _s, ch, msg in iter_salvaged_messages(mcap):
            topic = ch.topic
            if topic.endswith("/pipeline"):
                d = json.loads(msg.data)
                fr = _Frame(int(d["frame_id"]), int(d["sim_time_ns"]), int(d["t0_ns"]), d.get("t_state_ns"))
                v = topic[1:-len("/pipeline")]
                self.by_t0[(v, fr.t0_ns)] = self.by_id[(v, fr.frame_id)] = fr
                if fr.t_state_ns is not None:
                    states[fr.sim_ns] = int(fr.t_state_ns)
            elif topic == "/ground_truth":
                d = json.loads(msg.data)
                for e in d.get("egos", ()):
                    self.speed[(str(e["vehicle"]), int(d["sim_time_ns"]))] = float(e.get("speed_mps") or 0.0)
        self._sims = sorted(states)
        self._states = [states[s] for s in self._sims]
        if not self.camera:
            raise ConfigError(f"{mcap}: no run config in its metadata (a truncated run.mcap?): "
                              f"cannot write camera info")

    def exposure_ns(self, sim_ns: int, fallback_ns: int) -> int:
        """t_state of sim time ``sim_ns`` (monotonic ns): recorded, or interpolated
        between the camera instants around it, else ``fallback_ns``."""
        i = bisect.bisect_left(self._sims, sim_ns)
        if i < len(self._sims) and self._sims[i] == sim_ns:
            return self._states[i]
        if 0 < i < len(self._sims):
            s0, s1, t0, t1 = self._sims[i - 1], self._sims[i], self._states[i - 1], self._states[i]
            return t0 + (t1 - t0) * (sim_ns - s0) // (s1 - s0)
        return fallback_ns


def export(mcap: str | Path, out: str | Path, *, vehicles: Iterable[str] | None = None,
           sim_window_ns: tuple[int, int] | None = None) -> Bag:
    """Write the bag of ``mcap`` (a ``run.mcap`` or a case window file) into the new
    folder ``out``; only ``vehicles`` (default all) and, with ``sim_window_ns``, only
    what shows sim times in ``[start, end]``.

    Raises:
        ConfigError: ``out`` exists, or ``mcap`` is not a run's recording (one line).
    """
    src, dst = Path(mcap), Path(out)
    if dst.exists():
        raise ConfigError(f"{dst}: already exists; a bag is written into a new folder")
    if not src.is_file():
        raise ConfigError(f"{src}: no such recording")
    run = _Run(src)
    dst.mkdir(parents=True)
    w = _Writer(dst)
    try:
        _write_all(w, src, run, None if vehicles is None else set(vehicles), sim_window_ns)
        return w.finish()
    except BaseException:
        w.abort()
        raise


def _write_all(w: _Writer, src: Path, run: _Run, only: set[str] | None,
               window: tuple[int, int] | None) -> None:
    off, cam = run.offset_ns, run.camera
    fy = (float(cam["height"]) / 2) / math.tan(math.radians(float(cam["fovy_deg"])) / 2)
    w_px, h_px = int(cam["width"]), int(cam["height"])
    mapping = DriveMapping()
    entities: dict[str, tuple[float, float, float]] = {}
    static_done = False

    def inside(v: str | None, sim_ns: int) -> bool:
        return (v is None or only is None or v in only) and (window is None or window[0] <= sim_ns <= window[1])

    for _s, ch, msg in iter_salvaged_messages(src):
        topic, v = ch.topic, ch.topic.split("/")[1]
        if not static_done:
            static_done = True
            vs = sorted({k[0] for k in run.by_id} & (only or {k[0] for k in run.by_id}))
            w.write("/tf_static", _mount_tf(vs, cam, stamp_of(msg.log_time)), log_ns=msg.log_time,
                    pub_ns=msg.log_time, transient_local=True)
        if topic == "/ground_truth":
            d = json.loads(msg.data)
            sim = int(d["sim_time_ns"])
            for e in d.get("entities", ()):
                entities[str(e["name"])] = (float(e["x_m"]), float(e["y_m"]), float(e["heading_rad"]))
            if not inside(None, sim):
                continue
            t = run.exposure_ns(sim, msg.publish_time) + off
            stamp = stamp_of(t)
            w.write("/tf", TFMessage([TransformStamped(Header(stamp, "world"), n, Transform(
                Vector3(x, y, 0.0), Quaternion(0.0, 0.0, math.sin(h / 2), math.cos(h / 2))))
                for n, (x, y, h) in sorted(entities.items())]), log_ns=msg.log_time, pub_ns=t)
            for e in d.get("egos", ()):
                ev = str(e["vehicle"])
                if inside(ev, sim):
                    w.write(f"/{ev}/vehicle/twist", TwistStamped(Header(stamp, ev), Twist(Vector3(
                        float(e.get("speed_mps") or 0.0), 0.0, 0.0))), log_ns=msg.log_time, pub_ns=t)
        elif topic.endswith("/camera") and (fr := run.by_t0.get((v, msg.publish_time))) and inside(v, fr.sim_ns):
            d = json.loads(msg.data)
            header = Header(stamp_of((fr.t_state_ns or fr.t0_ns) + off), f"{v}/camera_optical_frame")
            data = base64.b64decode(d["data"])
            if "format" in d:
                w.write(f"/{v}/camera/image_raw/compressed", CompressedImage(header, str(d["format"]), data),
                        log_ns=msg.log_time, pub_ns=fr.t0_ns + off)
            else:
                w.write(f"/{v}/camera/image_raw", Image(header, int(d["height"]), int(d["width"]), str(d["encoding"]),
                                                        0, int(d["step"]), data), log_ns=msg.log_time,
                        pub_ns=fr.t0_ns + off)
            w.write(f"/{v}/camera/camera_info", camera_info_of(header, w_px, h_px, fy, fy, w_px / 2, h_px / 2),
                    log_ns=msg.log_time, pub_ns=fr.t0_ns + off)
        elif topic.endswith("/estimate") and (fr := run.by_id.get((v, _frame_id(msg.data)))) and \
                inside(v, fr.sim_ns):
            _write_estimate(w, v, json.loads(msg.data), fr, run, mapping, log_ns=msg.log_time)


def _frame_id(data: bytes) -> int:
    return int(json.loads(data)["frame_id"])


def _write_estimate(w: _Writer, v: str, d: dict[str, Any], fr: _Frame, run: _Run, mapping: DriveMapping, *,
                    log_ns: int) -> None:
    off = run.offset_ns
    header = Header(stamp_of((fr.t_state_ns or fr.t0_ns) + off), f"{v}/camera_optical_frame")
    pub = fr.t0_ns + off
    c = d.get("control") or {}
    control = Control(float(c.get("steering_rad", 0.0)), float(c.get("throttle", 0.0)), float(c.get("brake", 0.0)))
    state = DrivingState[str(d.get("state", "SAFE"))]
    objects = tuple(DetectedObject(ObjectClass[str(o["cls"])], float(o["confidence"]), tuple(o["box_px"]),
                                   tuple(o["position_m"])) for o in d.get("objects", ()))
    speed = run.speed.get((v, fr.sim_ns), 0.0)
    w.write(f"/{v}/detections", detections_of(objects, header), log_ns=log_ns, pub_ns=pub)
    w.write(f"/{v}/control", AckermannDriveStamped(header, mapping.drive_of(control, state, speed)), log_ns=log_ns,
            pub_ns=pub)
    w.write(f"/{v}/driving_state", String(state.name), log_ns=log_ns, pub_ns=pub)


def _mount_tf(vehicles: list[str], cam: dict[str, Any], stamp: Any) -> TFMessage:
    fwd, lat, height = (float(cam.get(k, 0.0)) for k in ("mount_forward_m", "mount_lateral_m", "mount_height_m"))
    q = mount_quaternion(math.radians(float(cam.get("pitch_deg", 0.0))), math.radians(float(cam.get("yaw_deg", 0.0))))
    out = []
    for v in vehicles:
        out.append(TransformStamped(Header(stamp, v), f"{v}/camera_link", Transform(Vector3(fwd, lat, height), q)))
        out.append(TransformStamped(Header(stamp, f"{v}/camera_link"), f"{v}/camera_optical_frame",
                                    Transform(Vector3(), OPTICAL_Q)))
    return TFMessage(out)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("rosbag", help="write a run, or one corner case's window, as a ROS 2 bag (rosbag2, MCAP)",
                       description="Write a run folder (or run.mcap, or a case's window file) as a rosbag2 folder "
                                   "that `ros2 bag play` feeds into a ROS 2 stack.")
    p.add_argument("run", type=Path, help="a run folder, its run.mcap, or a corner_cases/case-NNNN.mcap")
    p.add_argument("--case", type=int, default=None, metavar="ID",
                   help="only this corner case's vehicle and window (see hil cases RUN)")
    p.add_argument("--out", type=Path, default=None,
                   help="the bag folder to create (default: RUN/rosbag2, or RUN/rosbag2-case-ID)")


def cmd(args: Any) -> int:
    """``hil rosbag``: prints the bag's folder and its topics. Raises ConfigError (one line)."""
    src = Path(args.run)
    run_dir = src if src.is_dir() else src.parent
    mcap = src / "run.mcap" if src.is_dir() else src
    vehicles, window = None, None
    if args.case is not None:
        from hil.harness.cases.casebook import read_cases

        rows = {int(r["id"]): r for r in read_cases(run_dir)[0]}
        row = rows.get(args.case)
        if row is None:
            raise ConfigError(f"{run_dir}: no corner case {args.case} (cases: {sorted(rows) or 'none'})")
        vehicles = [str(row["vehicle"])]
        start, end = row.get("window_start_ns"), row.get("window_end_ns")
        window = (int(start), int(end)) if start is not None and end is not None else None
    out = args.out or run_dir / ("rosbag2" if args.case is None else f"rosbag2-case-{args.case:04d}")
    bag = export(mcap, out, vehicles=vehicles, sim_window_ns=window)
    print(f"{bag.path}: {sum(bag.counts.values())} messages, {(bag.end_ns - bag.start_ns) / 1e9:.2f} s "
          f"(ros2 bag play {bag.path})")
    for topic, n in sorted(bag.counts.items()):
        print(f"  {topic}: {n}")
    return 0


__all__ = ["ROS_DISTRO", "VERSION", "Bag", "add_parser", "cmd", "export", "qos_yaml"]
