"""Recorder benchmark: can ``hil.harness.record.recorder.Recorder`` keep up with a full run's load?

The load is what a 4-vehicle run at 20 fps records, generated synthetically at that
rate: per vehicle and frame one JPEG camera image (320x240, q85, ~12 KB, made with
OpenCV: sky, road, lane marks, a car, sensor noise), one estimate and one pipeline
record; per frame tick one ground-truth message; clock-sync samples at 1 Hz per
vehicle; events at ~2 per second.

1. Sustained: the load is enqueued at real-time pace for ``--duration`` seconds
   (default 30) into a recorder with the run's queue size (4096) and zstd; it must
   end with zero drops. Shows the producer's cost per tick (what the sim loop pays).
2. Throughput: the same messages enqueued flat out (queue large enough never to
   drop) for zstd, lz4 and no compression; MB/s and messages/s of message payload
   through the recorder (enqueue to closed file), next to a raw unbuffered file write
   of the same payload bytes in 1 MiB blocks in the same run (the floor), with the
   ratio; medians of ``--repeat`` tries.
3. What a message costs: µs to encode one message of each kind the run writes, with
   the standard library's JSON encoder (the recorder's until 2026-11), orjson (today's,
   ``hil.harness.record.encoding``) and msgspec (when installed); and a camera frame as
   JSON with base64 data (today's) against foxglove-sdk's protobuf, plus zstd of each.
4. Foxglove views: the writer thread's time per camera frame with the Foxglove views
   (annotations, calibration, transforms, log, latency; derived on the writer thread)
   and without, flat out; and the encode cost of one frame's ImageAnnotations as
   JSON (what is written) against foxglove-sdk's protobuf (``foxglove.messages``,
   objects built directly, then ``encode()``), when foxglove-sdk is installed.

    .venv/bin/python bench/bench_recorder.py [--duration 30] [--vehicles 4] [--fps 20]

Prints markdown tables. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.harness.record.channels import register_all
from hil.harness.record.recorder import Recorder, _image_json  # the exact bytes the writer makes

Msg = tuple[str, str, Any, int]  # (kind, topic, payload, log_time_ns)


def make_images(n: int, *, seed: int = 0, quality: int = 85) -> list[bytes]:
    """``n`` distinct 320x240 road-like JPEGs of about 12 KB each."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        img = np.zeros((240, 320, 3), np.uint8)
        img[:120] = np.linspace(235, 150, 120, dtype=np.uint8)[:, None, None] * np.array([1.0, 0.9, 0.75])
        img[120:] = (95, 95, 100)
        cv2.fillPoly(img, [np.array([[0, 240], [140, 120], [180, 120], [320, 240]])], (70, 70, 75))
        for k in range(6):
            y = 125 + k * 20
            cv2.line(img, (160, y), (160, y + 10), (230, 230, 230), 2)
        w = 20 + 5 * (i % 8)
        cv2.rectangle(img, (160 - w // 2, 150 - w // 3), (160 + w // 2, 150 + w // 3), (40, 40, 200), -1)
        noise = rng.normal(0, 5.5, img.shape)
        img = np.clip(img + noise, 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", img, (cv2.IMWRITE_JPEG_QUALITY, quality))
        assert ok
        out.append(buf.tobytes())
    return out


def tick_messages(k: int, t_ns: int, vehicles: list[str], images: list[bytes], period_ns: int,
                  rng: np.random.Generator) -> Iterator[Msg]:
    """The messages of camera tick ``k`` at harness time ``t_ns``."""
    sim_ns = k * period_ns
    for i, v in enumerate(vehicles):
        t0 = t_ns + i * 50_000
        yield "image", f"/{v}/camera", images[(k * len(vehicles) + i) % len(images)], t0
        t0p = t0 + 3_000_000
        yield "json", f"/{v}/estimate", {
            "frame_id": k, "state": "SAFE", "control": {"steering_rad": 0.001, "throttle": 0.3, "brake": 0.0},
            "objects": [{"cls": "VEHICLE", "confidence": 0.71, "box_px": [156.2, 119.1, 163.9, 125.3],
                         "position_m": [47.86, -0.02, 0.0]}]}, t0p
        yield "json", f"/{v}/pipeline", {
            "vehicle": v, "frame_id": k, "status": "ok", "sim_time_ns": sim_ns, "t0_ns": t0, "t_tx_ns": t0 + 300_000,
            "t_rx_target_ns": t0 + 500_000, "t_infer_start_target_ns": t0 + 600_000,
            "t_infer_end_target_ns": t0 + 2_600_000, "t_reply_target_ns": t0 + 2_700_000, "t0p_ns": t0p,
            "t_apply_ns": t0p + 100_000, "sim_time_apply_ns": sim_ns + 4_000_000,
            "stages_ns": {"capture_to_send": 300_000, "end_to_end": 3_000_000, "to_apply": 3_100_000,
                          "apply_delay": 100_000, "target_total": 2_200_000, "transport": 500_000,
                          "target_queue": 100_000, "inference": 2_000_000}}, t0p
        if k % 20 == 0:
            yield "json", f"/{v}/clock_sync", {
                "seq": k // 20, "t1_ns": t0, "t2_target_ns": t0 + 90_000, "t3_target_ns": t0 + 130_000,
                "t4_ns": t0 + 260_000, "offset_ns": -45_282.5, "delay_ns": 220_000}, t0 + 260_000
    yield "json", "/ground_truth", {
        "sim_time_ns": sim_ns,
        "entities": [{"name": n, "cls": "vehicle", "x_m": 1.0 * k, "y_m": -1.85, "vx_mps": 8.0, "vy_mps": 0.0,
                      "heading_rad": 0.0, "size_m": [4.5, 1.8, 1.4]} for n in [*vehicles, "car1", "car2"]],
        "egos": [{"vehicle": v, "gap_m": 45.0 - 0.4 * k, "obstacle": "car1", "speed_mps": 8.0,
                  "ref_state": "SAFE"} for v in vehicles]}, t_ns
    if rng.random() < 0.1:
        yield "json", "/events", {"kind": "latency_spike", "vehicle": vehicles[k % len(vehicles)], "frame_id": k,
                                  "value_ms": 41.2, "threshold_ms": 20.0, "severity": "warning"}, t_ns


CAMERA = {"width": 320, "height": 240, "fovy_deg": 60.0, "mount_forward_m": 2.3, "mount_lateral_m": 0.0,
          "mount_height_m": 1.3, "pitch_deg": 0.0}
META = {"config": {"yaml_json": json.dumps({"camera": CAMERA})}}


def with_truth(msgs: list[Msg]) -> list[Msg]:
    """``msgs`` with one camera-truth message (two visible boxes) before each image."""
    out: list[Msg] = []
    for m in msgs:
        if m[0] == "image":
            v = m[1].split("/")[1]
            boxes = [{"entity": f"car{j}", "id": j, "cls": "vehicle", "box_px": [150 + j, 118, 165 + j, 127],
                      "visible_px": 120, "visible_fraction": 1.0, "truncated": False, "path_s_m": 45.0 + j,
                      "path_lateral_m": 0.0} for j in (1, 2)]
            out.append(("json", f"/{v}/truth", {"vehicle": v, "frame_id": len(out), "sim_time_ns": 0,
                                                 "boxes": boxes, "ego": {}}, m[3]))
        out.append(m)
    return out


def views_cost(msgs: list[Msg], *, vehicles: list[str], folder: Path, repeat: int) -> dict[str, float]:
    """Writer-thread time per frame with and without the Foxglove views (flat out)."""
    frames = sum(1 for m in msgs if m[0] == "image")
    res = {}
    for views in (False, True):
        tries = []
        for _ in range(repeat):
            t = time.perf_counter()
            with Recorder(folder / "views.mcap", queue_size=len(msgs) + 16, compression="zstd",
                          metadata=META) as rec:
                register_all(rec, vehicles, views=views)
                for m in msgs:
                    _put(rec, m)
            tries.append(time.perf_counter() - t)
            assert rec.stats.errors == 0, rec.stats
        res["with" if views else "without"] = float(np.median(tries)) / frames * 1e6
    return res


def annotation_encode_cost(n: int) -> dict[str, float]:
    """µs to build and encode one frame's ImageAnnotations (2 truth + 1 AI box, 4
    labels): JSON as written, and foxglove-sdk protobuf (if installed)."""
    from hil.harness.record.foxglove_out import FoxgloveViews

    fv = FoxgloveViews(["ego0"], camera=CAMERA, offset_ns=0)
    boxes = [{"cls": "vehicle", "box_px": [150, 118, 165, 127], "path_s_m": 45.0}] * 2
    objs = [{"cls": "VEHICLE", "confidence": 0.7, "box_px": [149.0, 117.0, 166.0, 128.0],
             "position_m": [44.0, 0.1, 0.0]}]
    enc = json.JSONEncoder(separators=(",", ":"))
    t = time.perf_counter()
    for i in range(n):
        enc.encode(fv._annotations(10**12 + i, boxes, objs, note="frame 1: AI SAFE")).encode()
    out = {"json_us": (time.perf_counter() - t) / n * 1e6}
    try:
        import foxglove.messages as fm
    except ImportError:
        return out

    def color(r: float, g: float, b: float, a: float) -> Any:
        return fm.Color(r=r, g=g, b=b, a=a)

    t = time.perf_counter()
    for i in range(n):
        ts = fm.Timestamp(1000 + i, 5)
        points, texts = [], []
        for (x0, y0, x1, y1), c in [(b["box_px"], (0.1, 0.9, 0.2, 1.0)) for b in boxes] + \
                                   [(o["box_px"], (1.0, 0.2, 0.9, 1.0)) for o in objs]:
            points.append(fm.PointsAnnotation(
                timestamp=ts, type=fm.PointsAnnotationType.LineLoop,
                points=[fm.Point2(x=x0, y=y0), fm.Point2(x=x1, y=y0), fm.Point2(x=x1, y=y1), fm.Point2(x=x0, y=y1)],
                outline_color=color(*c), fill_color=color(*c[:3], 0.0), thickness=2.0))
            texts.append(fm.TextAnnotation(timestamp=ts, position=fm.Point2(x=x0, y=y1 + 12), text="truth vehicle 45.0 m",
                                           font_size=12.0, text_color=color(*c),
                                           background_color=color(0.0, 0.0, 0.0, 0.6)))
        texts.append(fm.TextAnnotation(timestamp=ts, position=fm.Point2(x=4, y=14), text="frame 1: AI SAFE",
                                       font_size=12.0, text_color=color(1, 1, 1, 1)))
        fm.ImageAnnotations(timestamp=ts, points=points, texts=texts).encode()
    out["protobuf_us"] = (time.perf_counter() - t) / n * 1e6
    return out


def message_costs(msgs: list[Msg], images: list[bytes], n: int = 3000) -> list[tuple[str, dict[str, float]]]:
    """µs per message to encode a sample of each kind, per encoder (module docstring, 3)."""
    from hil.harness.record.encoding import dumps

    std = json.JSONEncoder(separators=(",", ":"), allow_nan=False)
    encoders: dict[str, Any] = {"json (stdlib)": lambda o: std.encode(o).encode(), "orjson": dumps}
    try:
        import msgspec

        encoders["msgspec"] = msgspec.json.Encoder().encode
    except ImportError:
        pass
    sample: dict[str, Any] = {}
    for kind, topic, payload, _t in msgs:
        if kind == "json":
            sample.setdefault(topic.rsplit("/", 1)[-1], payload)
    rows = []
    for name, obj in sample.items():
        costs = {}
        for enc, fn in encoders.items():
            t = time.perf_counter()
            for _ in range(n):
                fn(obj)
            costs[enc] = (time.perf_counter() - t) / n * 1e6
        rows.append((f"{name} ({len(dumps(obj))} B)", costs))
    return rows


def image_costs(images: list[bytes], n: int = 2000) -> dict[str, float]:
    """µs to encode one JPEG camera frame as JSON with base64 data (today's) and as
    foxglove-sdk protobuf (if installed), and bytes after zstd of each."""
    import zstandard

    blob = images[0]
    z = zstandard.ZstdCompressor(level=3)
    t = time.perf_counter()
    for i in range(n):
        data = _image_json(10**18 + i, "ego0/camera", b'"format":"jpeg",', blob)
    out = {"json_us": (time.perf_counter() - t) / n * 1e6, "json_bytes": len(data),
           "json_zstd_bytes": len(z.compress(data)), "jpeg_bytes": len(blob)}
    try:
        import foxglove.messages as fm
    except ImportError:
        return out
    t = time.perf_counter()
    for i in range(n):
        pb = fm.CompressedImage(timestamp=fm.Timestamp(1_000_000 + i, 5), frame_id="ego0/camera", data=blob,
                                format="jpeg").encode()
    out.update(protobuf_us=(time.perf_counter() - t) / n * 1e6, protobuf_bytes=len(pb),
               protobuf_zstd_bytes=len(z.compress(pb)))
    return out


def _put(rec: Recorder, m: Msg) -> bool:
    kind, topic, payload, t = m
    if kind == "image":
        return rec.write_image(topic, payload, fmt="jpeg", frame_id=topic[1:], log_time_ns=t, publish_time_ns=t)
    return rec.write_json(topic, payload, log_time_ns=t, publish_time_ns=t)


def _payload_bytes(m: Msg) -> bytes:
    kind, topic, payload, t = m
    if kind == "image":
        return _image_json(t, topic[1:], b'"format":"jpeg",', payload)
    return json.dumps(payload, separators=(",", ":")).encode()


def sustained(folder: Path, *, vehicles: list[str], images: list[bytes], fps: float, duration_s: float,
              compression: str) -> dict[str, Any]:
    """Enqueue the load at real-time pace; returns the recorder's counters."""
    period_ns = int(1e9 / fps)
    rng = np.random.default_rng(1)
    ticks = int(duration_s * fps)
    cost_ns = np.zeros(ticks, np.int64)
    offered = 0
    path = folder / f"sustained-{compression}.mcap"
    cpu0 = time.process_time()
    with Recorder(path, queue_size=4096, compression=compression) as rec:
        register_all(rec, vehicles)
        start = time.monotonic_ns()
        for k in range(ticks):
            due = start + k * period_ns
            while (now := time.monotonic_ns()) < due:
                time.sleep(min((due - now) / 1e9, 0.005))
            t = time.monotonic_ns()
            n = 0
            for m in tick_messages(k, t, vehicles, images, period_ns, rng):
                _put(rec, m)
                n += 1
            cost_ns[k] = time.monotonic_ns() - t
            offered += n
        enq_end = time.monotonic_ns()
    close_ns = time.monotonic_ns() - enq_end
    st = rec.stats
    return {"ticks": ticks, "offered": offered, "written": st.written, "dropped": st.dropped,
            "errors": st.errors, "max_depth": st.max_queue_depth, "bytes": st.bytes_written,
            "wall_s": (enq_end - start) / 1e9, "close_ms": close_ns / 1e6,
            "cpu_s": time.process_time() - cpu0,
            "tick_p50_us": float(np.percentile(cost_ns, 50)) / 1e3,
            "tick_p99_us": float(np.percentile(cost_ns, 99)) / 1e3}


def throughput(folder: Path, msgs: list[Msg], payload: int, *, vehicles: list[str],
               compression: str) -> dict[str, Any]:
    """The same messages flat out through the recorder (queue never full)."""
    path = folder / f"flat-{compression}.mcap"
    t = time.perf_counter()
    with Recorder(path, queue_size=len(msgs) + 16, compression=compression) as rec:
        register_all(rec, vehicles)
        for m in msgs:
            _put(rec, m)
    dt = time.perf_counter() - t
    st = rec.stats
    assert st.dropped == 0 and st.errors == 0, st
    return {"s": dt, "mb_s": payload / dt / 1e6, "msg_s": len(msgs) / dt, "file_mb": st.bytes_written / 1e6}


def raw_write(folder: Path, blobs: list[bytes]) -> float:
    """Seconds to write ``blobs`` to a file unbuffered, in 1 MiB blocks (the floor)."""
    path = folder / "raw.bin"
    t = time.perf_counter()
    block: list[bytes] = []
    size = 0
    with open(path, "wb", buffering=0) as f:
        for b in blobs:
            block.append(b)
            size += len(b)
            if size >= 1 << 20:
                f.write(b"".join(block))
                block, size = [], 0
        if block:
            f.write(b"".join(block))
    dt = time.perf_counter() - t
    path.unlink()
    return dt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=30.0, help="seconds of load (default 30)")
    p.add_argument("--vehicles", type=int, default=4)
    p.add_argument("--fps", type=float, default=20.0)
    p.add_argument("--repeat", type=int, default=5, help="flat-out tries per writer; the median is shown")
    p.add_argument("--dir", type=Path, default=None, help="where to write (default a temp folder)")
    a = p.parse_args(argv)
    vehicles = [f"ego{i}" for i in range(a.vehicles)]
    images = make_images(256)  # more than a chunk holds: no repeats for zstd to exploit
    print(f"load: {a.vehicles} vehicles x {a.fps:g} fps x {a.duration:g} s; JPEG 320x240 q85, "
          f"mean {np.mean([len(i) for i in images]) / 1e3:.1f} KB (min {min(map(len, images)) / 1e3:.1f}, "
          f"max {max(map(len, images)) / 1e3:.1f})\n")
    with tempfile.TemporaryDirectory(dir=a.dir) as tmp:
        folder = Path(tmp)
        s = sustained(folder, vehicles=vehicles, images=images, fps=a.fps, duration_s=a.duration, compression="zstd")
        print("## Sustained, real-time pace (queue 4096, zstd)\n")
        print("| ticks | messages | msg/s | written | dropped | errors | max queue depth | file MB "
              "| producer per tick p50 / p99 (µs) | CPU s / wall s | close (ms) |")
        print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        print(f"| {s['ticks']} | {s['offered']} | {s['offered'] / s['wall_s']:.0f} | {s['written']} | "
              f"{s['dropped']} | {s['errors']} | {s['max_depth']} | {s['bytes'] / 1e6:.1f} | "
              f"{s['tick_p50_us']:.0f} / {s['tick_p99_us']:.0f} | {s['cpu_s']:.2f} / {s['wall_s']:.1f} | "
              f"{s['close_ms']:.0f} |\n")
        period_ns = int(1e9 / a.fps)
        rng = np.random.default_rng(1)
        msgs = [m for k in range(int(a.duration * a.fps))
                for m in tick_messages(k, 10**12 + k * period_ns, vehicles, images, period_ns, rng)]
        blobs = [_payload_bytes(m) for m in msgs]
        payload = sum(map(len, blobs))
        print(f"## Throughput, flat out: {len(msgs)} messages, {payload / 1e6:.1f} MB of message payload\n")
        print("| writer | time (s) | MB/s | messages/s | file MB | raw write (s) | raw MB/s | MCAP / raw |")
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        rates: dict[str, float] = {}
        for comp in ("zstd", "lz4", "none"):
            # Median of a few tries: each is a fraction of a second.
            tries = sorted((throughput(folder, msgs, payload, vehicles=vehicles, compression=comp)
                            for _ in range(a.repeat)), key=lambda r: r["s"])
            r = tries[len(tries) // 2]
            raw_s = float(np.median([raw_write(folder, blobs) for _ in range(a.repeat)]))
            raw_mb_s = payload / raw_s / 1e6
            rates[comp] = r["mb_s"]
            print(f"| Recorder, {comp} | {r['s']:.3f} | {r['mb_s']:.0f} | {r['msg_s']:.0f} | {r['file_mb']:.1f} | "
                  f"{raw_s:.3f} | {raw_mb_s:.0f} | {r['mb_s'] / raw_mb_s:.3f} |")
        need = payload / a.duration / 1e6
        print(f"\nThe run's load needs {need:.2f} MB/s and {len(msgs) / a.duration:.0f} messages/s: "
              f"headroom x{rates['zstd'] / need:.0f} with zstd (the run's choice), x{rates['lz4'] / need:.0f} "
              f"with lz4.")
        print("\n## What a message costs (encode only, µs per message)\n")
        rows = message_costs(with_truth(msgs), images)
        names = list(rows[0][1])
        print("| message | " + " | ".join(names) + " | stdlib / orjson |")
        print("| --- | " + " | ".join("---:" for _ in names) + " | ---: |")
        for label, costs in rows:
            print(f"| {label} | " + " | ".join(f"{costs[k]:.1f}" for k in names)
                  + f" | {costs['json (stdlib)'] / costs['orjson']:.1f}x |")
        ic = image_costs(images)
        print("\n| one JPEG camera frame | encode (µs) | bytes | after zstd |")
        print("| --- | ---: | ---: | ---: |")
        print(f"| JSON, base64 data (written) | {ic['json_us']:.1f} | {ic['json_bytes']} | {ic['json_zstd_bytes']} |")
        if "protobuf_us" in ic:
            print(f"| foxglove-sdk protobuf | {ic['protobuf_us']:.1f} | {ic['protobuf_bytes']} | "
                  f"{ic['protobuf_zstd_bytes']} |")
        print("\n## Foxglove views (writer thread, zstd, flat out; each camera frame has 2 true boxes)\n")
        vmsgs = with_truth(msgs)
        vc = views_cost(vmsgs, vehicles=vehicles, folder=folder, repeat=a.repeat)
        ac = annotation_encode_cost(2000)
        print("| writer time per camera frame, hil.* only (µs) | with Foxglove views (µs) | views cost (µs) |")
        print("| ---: | ---: | ---: |")
        print(f"| {vc['without']:.0f} | {vc['with']:.0f} | {vc['with'] - vc['without']:.0f} |\n")
        print("| one frame's ImageAnnotations | build + encode (µs) |")
        print("| --- | ---: |")
        print(f"| JSON (written today) | {ac['json_us']:.1f} |")
        print(f"| foxglove-sdk protobuf | {ac['protobuf_us']:.1f} |" if "protobuf_us" in ac
              else "| foxglove-sdk protobuf | not installed |")
        if s["dropped"]:
            print(f"FAIL: {s['dropped']} messages dropped at real-time pace")
            return 1
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    raise SystemExit(main())
