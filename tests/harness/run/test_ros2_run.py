"""Whole runs against a ROS 2 node (hil_configs/ros2.yaml: the OpenCV baseline as a
ROS 2 node on Cyclone DDS, started by the harness in a domain of the run's own):
end-to-end and to-apply exact, the stages that need target stamps unknown (never 0),
the node's clock offset within its stated bound of the truth this host knows, and
the rosbag2 folder read back with rosbags (topics, types, counts, stamps) and its
schemas parsed by mcap-ros2-support (neither is the writer)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from hil.harness.config.loading import load_config
from hil.harness.run.driver import execute, prepare_out_dir
from tests.conftest import GL_BACKEND, read_mcap

ROOT = Path(__file__).resolve().parents[3]
TARGET_STAGES = ("target_queue", "inference", "target_total", "transport")


@pytest.fixture(scope="module")
def ros2_run(tmp_path_factory):
    cfg = load_config(ROOT / "hil_configs/ros2.yaml", overrides=["duration_s=2", "progress=false"])
    return execute(cfg, out_dir=prepare_out_dir(tmp_path_factory.mktemp("ros2") / "r"), gl_backend=GL_BACKEND,
                   install_signal_handlers=False)


def test_stages_without_target_stamps_are_unknown_and_the_rest_exact(ros2_run) -> None:
    s = ros2_run.summary
    v = s["vehicles"]["ego0"]
    assert s["ended_by"] == "duration" and v["frames_sent"] == 40
    assert v["estimates_applied"] + v["dropped"] + v["stale"] == 40 and v["estimates_applied"] >= 36
    assert v["target"] == {"name": "cv-baseline", "clock": "REALTIME", "clock_resolution_ns": 1}
    recs = [d for _, d in read_mcap(ros2_run.mcap_path)["/ego0/pipeline"]]
    ok = [r for r in recs if r["status"] == "ok"]
    assert len(ok) == v["estimates_applied"]
    for r in ok:
        assert r["t_rx_target_ns"] is None and r["t_infer_start_target_ns"] is None
        assert r["t_infer_end_target_ns"] is None and r["t_reply_target_ns"] > 0  # the DDS write time
        st = r["stages_ns"]
        assert st["end_to_end"] == r["t0p_ns"] - r["t0_ns"] and st["to_apply"] == r["t_apply_ns"] - r["t0_ns"]
        assert not set(TARGET_STAGES) & set(st)
    lat = v["latency_ms"]
    for stage in TARGET_STAGES:
        assert lat[stage] == {"count": 0}  # unknown, not zero
    e2e = np.array([r["stages_ns"]["end_to_end"] for r in ok]) / 1e6
    assert lat["end_to_end"]["count"] == len(ok)
    assert lat["end_to_end"]["p50_ms"] == pytest.approx(float(np.percentile(e2e, 50)), abs=1e-4)
    assert v["splits_ms"]["uplink"] == {"count": 0}
    t = v["link"]["transport"]
    # the reference node copies the image's header into both answers: every part matched by stamp
    assert t["matched_by_stamp"] >= 2 * v["estimates_applied"] and t["matched_by_arrival"] == 0
    assert (t["foreign_samples"], t["malformed"], t["type_mismatches"]) == (0, 0, [])
    assert 100 <= t["domain_id"] <= 232  # the run's own domain


def test_the_nodes_clock_offset_is_within_its_bound(ros2_run) -> None:
    clock = ros2_run.summary["vehicles"]["ego0"]["clock"]
    assert clock["samples_used"] > 0 and clock["uncertainty_ns"] > 0
    truth = time.time_ns() - time.monotonic_ns()  # the node's system clock against ours: same host
    assert abs(clock["offset_ns"] - truth) <= clock["uncertainty_ns"] + 2_000_000  # + NTP slewing since


def test_rosbag2_reads_back_with_rosbags(ros2_run) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    bag = ros2_run.out_dir / "rosbag2"
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "rosbag2_0.mcap"]
    mcap = read_mcap(ros2_run.mcap_path)
    recs = {d["frame_id"]: d for _, d in mcap["/ego0/pipeline"]}
    answered = [d["frame_id"] for _, d in mcap["/ego0/estimate"]]
    offset = mcap["/ground_truth"][0][0].log_time - mcap["/ground_truth"][0][0].publish_time
    want = {"/tf_static": ("tf2_msgs/msg/TFMessage", 1),
            "/tf": ("tf2_msgs/msg/TFMessage", len(mcap["/ground_truth"])),
            "/ego0/vehicle/twist": ("geometry_msgs/msg/TwistStamped", len(mcap["/ground_truth"])),
            "/ego0/camera/image_raw/compressed": ("sensor_msgs/msg/CompressedImage", len(recs)),
            "/ego0/camera/camera_info": ("sensor_msgs/msg/CameraInfo", len(recs)),
            "/ego0/detections": ("vision_msgs/msg/Detection2DArray", len(answered)),
            "/ego0/control": ("ackermann_msgs/msg/AckermannDriveStamped", len(answered)),
            "/ego0/driving_state": ("std_msgs/msg/String", len(answered))}
    stamps: dict[str, list[int]] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == want
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in reader.connections}
        assert qos["/tf_static"].durability.name == "TRANSIENT_LOCAL" and qos["/tf"].durability.name == "VOLATILE"
        for conn, log_time, raw in reader.messages():
            m = reader.deserialize(raw, conn.msgtype)
            if hasattr(m, "header"):
                stamps.setdefault(conn.topic, []).append(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)
            if conn.topic == "/ego0/control":
                assert m.header.frame_id == "ego0/camera_optical_frame"
    # header stamps: the exposure instant of each frame on the run's wall-clock timeline
    exposure = sorted(r["t_state_ns"] + offset for r in recs.values())
    assert sorted(stamps["/ego0/camera/image_raw/compressed"]) == exposure
    assert sorted(stamps["/ego0/control"]) == sorted(recs[f]["t_state_ns"] + offset for f in answered)
    # publish_time is the capture time t0 (read with mcap, rosbags does not expose it)
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    pubs, decoded = [], 0
    with open(bag / "rosbag2_0.mcap", "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        assert r.get_header().profile == "ros2"
        for schema, channel, msg, ros in r.iter_decoded_messages():
            decoded += 1  # mcap-ros2-support parsed the schema text and the CDR on its own
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            assert "offered_qos_profiles" in channel.metadata
            if channel.topic == "/ego0/camera/image_raw/compressed":
                pubs.append(msg.publish_time)
                assert ros.format == "jpeg"
    assert decoded == sum(n for _, n in want.values())
    assert sorted(pubs) == sorted(r["t0_ns"] + offset for r in recs.values())
    assert ros2_run.summary["rosbag2"]["messages"] == decoded


@pytest.mark.slow
def test_realtime_on_the_system_clock(tmp_path) -> None:
    cfg = load_config(ROOT / "hil_configs/ros2.yaml", overrides=[
        "duration_s=2", "progress=false", "mode=realtime", "target.ros2.clock=system", "recording.rosbag2=false"])
    r = execute(cfg, out_dir=prepare_out_dir(tmp_path / "r"), gl_backend=GL_BACKEND, install_signal_handlers=False)
    v = r.summary["vehicles"]["ego0"]
    assert r.summary["ended_by"] == "duration" and v["estimates_applied"] >= 0.8 * v["frames_sent"]
    t = v["link"]["transport"]
    assert t["clock"] == "system" and t["matched_by_stamp"] >= v["estimates_applied"]
    assert "rosbag2" not in r.summary and not (r.out_dir / "rosbag2").exists()


def test_a_window_of_the_run_as_a_bag(ros2_run, tmp_path) -> None:
    from hil.harness.report.rosbag2 import export

    mcap = read_mcap(ros2_run.mcap_path)
    window = (500_000_000, 1_000_000_000)
    inside = [d for _, d in mcap["/ego0/pipeline"] if window[0] <= d["sim_time_ns"] <= window[1]]
    truths = [d for _, d in mcap["/ground_truth"] if window[0] <= d["sim_time_ns"] <= window[1]]
    bag = export(ros2_run.mcap_path, tmp_path / "w", vehicles=["ego0"], sim_window_ns=window)
    assert 0 < len(inside) < 40
    assert bag.counts["/ego0/camera/image_raw/compressed"] == len(inside)
    assert bag.counts["/tf"] == len(truths) and bag.counts["/tf_static"] == 1
    assert export(ros2_run.mcap_path, tmp_path / "none", vehicles=["nobody"]).counts.keys() == {
        "/tf", "/tf_static"}  # another vehicle's frames are left out; the world is shared


def test_hil_rosbag_command_and_its_mistakes(ros2_run, tmp_path) -> None:
    from tests.harness.cli.test_cli import assert_one_line_error, hil

    out = tmp_path / "bag"
    p = hil("rosbag", str(ros2_run.out_dir), "--out", str(out))
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith(f"{out}: {ros2_run.summary['rosbag2']['messages']} messages")
    assert (out / "metadata.yaml").is_file() and (out / "bag_0.mcap").is_file()
    assert_one_line_error(hil("rosbag", str(ros2_run.out_dir), "--out", str(out)), "already exists")
    assert_one_line_error(hil("rosbag", str(ros2_run.out_dir), "--case", "999", "--out", str(tmp_path / "c")),
                          "no corner case 999")
    assert_one_line_error(hil("rosbag", str(tmp_path / "missing")), "no such recording")


def test_bad_ros2_config_is_one_line_before_anything_starts() -> None:
    from hil.common.errors import ConfigError

    with pytest.raises(ConfigError, match=r"target\.ros2\.topics\.control.*fully qualified ROS 2 topic"):
        load_config(ROOT / "hil_configs/ros2.yaml", overrides=["target.ros2.topics.control=cmd"])
    with pytest.raises(ConfigError, match=r"target\.ros2\.domain_id"):
        load_config(ROOT / "hil_configs/ros2.yaml", overrides=["target.ros2.domain_id=233"])
    with pytest.raises(ConfigError, match=r"target\.shared"):
        load_config(ROOT / "hil_configs/ros2.yaml", overrides=["target.shared=true"])
