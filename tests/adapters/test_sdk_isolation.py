"""The target SDK must run on a device with only numpy and its transport: import it
in a clean interpreter where the simulator, torch, OpenCV and harness code are
blocked, and serve a frame through the local transport."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

BLOCKER = textwrap.dedent("""
    import sys
    BLOCKED = ("mujoco", "torch", "cv2", "harness", "scenarios", "targets", "zenoh", "can",
               "mcap", "pydantic", "rich", "yaml")
    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"blocked on a device: {name}")
            return None
    sys.meta_path.insert(0, Block())
""")


def test_sdk_imports_without_heavy_modules():
    code = BLOCKER + textwrap.dedent("""
        from hil.adapters.sdk import Endpoint, serve, decode_image
        import hil.adapters.sdk, hil.adapters.wire.protocol, hil.adapters.wire.messages
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        print("LOADED", loaded)
    """)
    p = subprocess.run([sys.executable, "-I", "-c", code], cwd=ROOT, capture_output=True, text=True,
                       env={"PYTHONPATH": str(ROOT)}, timeout=60)
    assert p.returncode == 0, p.stderr
    assert "LOADED []" in p.stdout


def test_blocked_sdk_serves_a_frame(tmp_path):
    # A target program using only the SDK, run by the real local link under the blocker.
    prog = tmp_path / "device_ai.py"
    prog.write_text(BLOCKER + textwrap.dedent("""
        from hil.adapters.sdk import decode_image, serve
        from hil.adapters.wire.messages import Control, DrivingState, Inference
        def infer(frame):
            img = decode_image(frame)
            return Inference(DrivingState.STOP, Control(brake=float(img.mean()) / 255.0))
        serve(infer, target_name="device")
    """))
    from hil.adapters.link import open_link
    from hil.adapters.wire.messages import CameraInfo, Estimate, ImageEncoding
    from hil.timing.clock import MonotonicClock

    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    link = open_link("local", command=[sys.executable, "-I", str(prog)], vehicle_id=0, clock=MonotonicClock(),
                     log_path=tmp_path / "t.log", env=env)
    try:
        link.open(hello_timeout_s=30)
        link.send_frame(frame_id=3, sim_time_ns=0, t0_ns=0, width=4, height=2, encoding=ImageEncoding.RGB8,
                        camera=CameraInfo(1, 1, 2, 1, 1.3), ego_speed_mps=0.0, data=bytes([51] * 24))
        r = link.recv(timeout_s=10)
        while r is not None and not isinstance(r.msg, Estimate):
            r = link.recv(timeout_s=10)
        assert r is not None, (tmp_path / "t.log").read_text()
        assert r.msg.frame_id == 3 and abs(r.msg.control.brake - 0.2) < 1e-6
    finally:
        link.close()
