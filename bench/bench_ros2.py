"""ROS 2 transport benchmark: the CDR codec against Cyclone's own serializer, and a
frame's round trip through the ros2 transport next to a raw Cyclone DDS floor, both
measured in this run.

Run: ``.venv/bin/python bench/bench_ros2.py`` (under a minute; ``--rounds``). Prints
markdown tables. Not part of the test suite.

Codec: µs per 320x240 raw ``sensor_msgs/Image`` (230 400 pixel bytes) and per JPEG
``CompressedImage`` (~12 KB), encoded and decoded by hil.adapters.ros2.cdr and by
Cyclone's ``IdlStruct.serialize``/``deserialize``; the floor is one copy of the bytes.

Round trip: ``Link.send_frame`` to the ESTIMATE out of ``Link.recv``, to the echo
target served as a ROS 2 node (``python -m hil.targets.echo --transport ros2``, a
child process, its own DDS domain): the image, camera info and speed out, an
AckermannDriveStamped and a Detection2DArray back. Floor: a child process that takes
the image's CDR bytes on one raw Cyclone reader and writes an AckermannDriveStamped
back at once (one topic each way, no decoding), timed the same way.
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.adapters.link import open_link  # noqa: E402
from hil.adapters.ros2 import cdr as ros2_cdr  # noqa: E402
from hil.adapters.ros2.dds import Participant, take, write  # noqa: E402
from hil.adapters.ros2.msgs import AckermannDriveStamped, CompressedImage, Header, Image, Time  # noqa: E402
from hil.adapters.ros2.options import IMAGE_QOS, REPLY_QOS, Ros2Options, cyclone_xml, node_env  # noqa: E402
from hil.adapters.wire.messages import CameraInfo, Estimate, ImageEncoding  # noqa: E402
from hil.timing.clock import MonotonicClock  # noqa: E402

CAM = CameraInfo(277.0, 277.0, 160.0, 120.0, 1.3)
FLOOR_NODE = """
import sys
from hil.adapters.ros2.dds import Participant, take, write
from hil.adapters.ros2.msgs import AckermannDriveStamped, CompressedImage, Image
from hil.adapters.ros2.options import IMAGE_QOS, REPLY_QOS, cyclone_xml
from cyclonedds.core import WaitSet, ReadCondition, SampleState, ViewState, InstanceState
with Participant(domain_id=int(sys.argv[1]), config=cyclone_xml(), name="floor") as p:
    cls = CompressedImage if sys.argv[2] == "jpeg" else Image
    r = p.reader("/camera/image", cls, IMAGE_QOS)
    w = p.writer("/control", AckermannDriveStamped, REPLY_QOS)
    ws = WaitSet(p.dp)
    ws.attach(ReadCondition(r, SampleState.Any | ViewState.Any | InstanceState.Any))
    reply = AckermannDriveStamped()
    while True:
        ws.wait(10**9)
        for _data, _info in take(r):
            write(w, reply)
"""


def pct(a: list[int]) -> tuple[float, float]:
    x = np.array(a) / 1e3
    return float(np.percentile(x, 50)), float(np.percentile(x, 99))


def codec_table(rounds: int) -> None:
    import cv2

    rgb = np.random.default_rng(1).integers(0, 256, (240, 320, 3), np.uint8)
    jpeg = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes()
    msgs = {"raw Image": Image(Header(Time(1, 2), "cam"), 240, 320, "rgb8", 0, 960, rgb.tobytes()),
            f"JPEG CompressedImage ({len(jpeg) // 1024} KB)": CompressedImage(Header(Time(1, 2), "cam"), "jpeg", jpeg)}
    print("| message | copy floor µs | ours encode µs | Cyclone serialize µs | ours decode µs "
          "| Cyclone deserialize µs |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, m in msgs.items():
        data = ros2_cdr.encode(m)
        t: dict[str, list[int]] = {k: [] for k in ("copy", "enc", "cy_enc", "dec", "cy_dec")}
        for _ in range(rounds):
            for key, fn in (("copy", lambda: bytearray(m.data)), ("enc", lambda: ros2_cdr.encode(m)),
                            ("cy_enc", m.serialize), ("dec", lambda: ros2_cdr.decode(type(m), data)),
                            ("cy_dec", lambda: type(m).deserialize(data))):
                t0 = time.perf_counter_ns()
                fn()
                t[key].append(time.perf_counter_ns() - t0)
        cells = [f"{pct(t[k])[0]:.1f}" for k in ("copy", "enc", "cy_enc", "dec", "cy_dec")]
        print(f"| {name} | " + " | ".join(cells) + " |")


def floor_round_trips(rounds: int, jpeg: bytes | None) -> list[int]:
    dom = random.randrange(150, 233)
    child = subprocess.Popen([sys.executable, "-c", FLOOR_NODE, str(dom), "jpeg" if jpeg else "raw"],
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
    out: list[int] = []
    try:
        with Participant(domain_id=dom, config=cyclone_xml(), name="bench") as p:
            cls = CompressedImage if jpeg else Image
            w = p.writer("/camera/image", cls, IMAGE_QOS)
            r = p.reader("/control", AckermannDriveStamped, REPLY_QOS)
            deadline = time.monotonic() + 20
            while not (w.get_matched_subscriptions() and r.get_matched_publications()):
                if time.monotonic() > deadline:
                    raise SystemExit("floor node did not match")
                time.sleep(0.01)
            msg = CompressedImage(Header(), "jpeg", jpeg) if jpeg else Image(Header(), 240, 320, "rgb8", 0, 960,
                                                                              bytes(230400))
            for _ in range(rounds + 20):
                t0 = time.monotonic_ns()
                write(w, msg)
                while not take(r):
                    pass
                out.append(time.monotonic_ns() - t0)
    finally:
        child.terminate()
        child.wait(10)
    return out[20:]


def link_round_trips(rounds: int, jpeg: bytes | None) -> list[int]:
    dom = random.randrange(150, 233)
    env = dict(os.environ, PYTHONPATH=str(ROOT), **node_env(dom, cyclone_xml()))
    child = subprocess.Popen([sys.executable, "-m", "hil.targets.echo", "--transport", "ros2"], env=env)
    link = open_link("ros2", vehicle_id=0, clock=MonotonicClock(),
                     options=Ros2Options(domain_id=dom, compressed=jpeg is not None))  # image_transport's topics
    out: list[int] = []
    try:
        link.open(hello_timeout_s=30)
        data = jpeg if jpeg else bytes(230400)
        for fid in range(rounds + 20):
            t0 = time.monotonic_ns()
            link.send_frame(frame_id=fid, sim_time_ns=fid + 1, t0_ns=t0, width=320, height=240,
                            encoding=ImageEncoding.JPEG if jpeg else ImageEncoding.RGB8, camera=CAM,
                            ego_speed_mps=5.0, data=data)
            while True:
                r = link.recv(timeout_s=5)
                if r is None:
                    raise SystemExit(f"no estimate for frame {fid}")
                if isinstance(r.msg, Estimate):
                    break
            out.append(time.monotonic_ns() - t0)
    finally:
        link.close()
        child.terminate()
        child.wait(10)
    return out[20:]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=300)
    a = ap.parse_args()
    import cv2

    sys.setswitchinterval(0.0001)  # as the run process sets it (harness/run/loop.py)

    print(f"load average: {os.getloadavg()[0]:.2f}\n")
    codec_table(a.rounds)
    rgb = np.random.default_rng(1).integers(0, 256, (240, 320, 3), np.uint8)
    jpeg = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes()
    print("\n| frame | raw Cyclone floor p50/p99 µs | ros2 transport p50/p99 µs | p50 ratio |")
    print("|---|---:|---:|---:|")
    for name, j in (("raw 320x240", None), ("JPEG", jpeg)):
        f50, f99 = pct(floor_round_trips(a.rounds, j))
        l50, l99 = pct(link_round_trips(a.rounds, j))
        print(f"| {name} | {f50:.0f} / {f99:.0f} | {l50:.0f} / {l99:.0f} | {l50 / f50:.2f} |")
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
