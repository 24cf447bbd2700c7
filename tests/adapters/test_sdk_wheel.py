"""The standalone SDK distribution: build the ``hil-target-sdk`` wheel, install it
with pip into a fresh virtualenv that has nothing else (numpy, its one dependency,
is lent from this environment), and serve a real harness run from there."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fresh_python(tmp_path_factory) -> Path:
    """A new virtualenv's python with only the SDK wheel installed (and numpy)."""
    base = tmp_path_factory.mktemp("sdk")
    out = subprocess.run([sys.executable, str(ROOT / "sdk" / "build_wheel.py"), "--out", str(base / "dist")],
                         capture_output=True, text=True, check=True)
    wheel = Path(out.stdout.strip())
    env_dir = base / "device-venv"
    venv.EnvBuilder(with_pip=False, system_site_packages=False).create(env_dir)
    py = env_dir / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
                    "--no-cache-dir", "--quiet", str(wheel)], check=True, capture_output=True, timeout=300)
    # numpy, and nothing else, from this environment: a folder holding only it.
    import numpy

    lent = base / "numpy-only"
    lent.mkdir()
    np_dir = Path(numpy.__file__).parent
    for p in (np_dir, np_dir.parent / "numpy.libs"):
        if p.exists():
            (lent / p.name).symlink_to(p)
    site = next((env_dir / "lib").glob("python3*/site-packages"))
    (site / "numpy-only.pth").write_text(str(lent) + "\n")
    return py


def test_wheel_holds_the_target_side_only(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "sdk" / "build_wheel.py"), "--out", str(tmp_path)],
                         capture_output=True, text=True, check=True)
    with zipfile.ZipFile(out.stdout.strip()) as z:
        names = z.namelist()
        meta = z.read(next(n for n in names if n.endswith("/METADATA"))).decode()
    tops = {"/".join(n.split("/")[:2]) for n in names}
    assert tops == {"hil/adapters", "hil/timing", "hil/common", "hil_target_sdk-0.1.0.dist-info/METADATA",
                    "hil_target_sdk-0.1.0.dist-info/WHEEL", "hil_target_sdk-0.1.0.dist-info/RECORD",
                    "hil_target_sdk-0.1.0.dist-info/top_level.txt"}
    assert {"hil/adapters/sdk.py", "hil/adapters/tcp/link.py", "hil/adapters/can/hil.dbc", "hil/timing/clock.py",
            "hil/common/errors.py", "hil/adapters/ros2/msg/vision_msgs/msg/Detection2D.msg"} <= set(names)
    # Every package of the SDK's folders is listed in sdk/pyproject.toml, so the wheel has it whole.
    packages = {"/".join(("hil", *p.relative_to(ROOT).parent.parts)) for folder in ("adapters", "timing", "common")
                for p in (ROOT / folder).rglob("__init__.py")}
    assert packages == {n.removesuffix("/__init__.py") for n in names if n.endswith("/__init__.py")}
    for package in packages:
        assert {f"{package}/{p.name}" for p in (ROOT / package.removeprefix("hil/")).glob("*.py")} <= set(names)
    assert not any(n.startswith("hil/__init__") for n in names)  # hil is a namespace shared with the harness
    required = [ln for ln in meta.splitlines() if ln.startswith("Requires-Dist:") and "extra ==" not in ln]
    assert required == ["Requires-Dist: numpy>=1.26,<2.5"]


def test_bad_out_is_one_line_and_exit_2(tmp_path):
    f = tmp_path / "a-file"
    f.write_text("")
    p = subprocess.run([sys.executable, str(ROOT / "sdk" / "build_wheel.py"), "--out", str(f)],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "is a file, not a folder" in p.stderr and len(p.stderr.splitlines()) == 1


@pytest.mark.slow
def test_fresh_venv_has_the_sdk_and_nothing_heavy(fresh_python, tmp_path):
    code = textwrap.dedent("""
        import importlib, hil.adapters.sdk, hil.adapters.tcp.link, hil.adapters.local.link
        print("SDK", hil.adapters.sdk.__file__)
        for name in ("mujoco", "cv2", "pydantic", "scipy", "hil.harness", "hil.scenarios", "hil.targets", "zenoh", "can"):
            try:
                importlib.import_module(name)
                print("HAS", name)
            except ImportError:
                pass
    """)
    p = subprocess.run([str(fresh_python), "-I", "-c", code], cwd=tmp_path, capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    assert f"SDK {fresh_python.parents[1]}" in p.stdout  # the installed copy, not this repository's
    assert "HAS" not in p.stdout, p.stdout


@pytest.mark.slow
def test_fresh_venv_serves_a_real_run(fresh_python, tmp_path):
    from hil.harness.config.loading import load_config
    from hil.harness.run.driver import execute, prepare_out_dir
    from tests.conftest import GL_BACKEND

    prog = tmp_path / "device_ai.py"
    prog.write_text(textwrap.dedent("""
        from hil.adapters.sdk import decode_image, serve
        from hil.adapters.wire.messages import Control, DrivingState, Inference

        def infer(frame):
            img = decode_image(frame)
            h, w = img.shape[:2]
            dark = img[h // 3: h - h // 3, w // 3: w - w // 3].mean() < 40
            return Inference(DrivingState.STOP if dark else DrivingState.SAFE,
                             Control(throttle=0.0 if dark else 0.3, brake=1.0 if dark else 0.0))

        serve(infer, target_name="wheel-device")
    """))
    cfg_path = tmp_path / "w.yaml"
    cfg_path.write_text("name: sdk-wheel\nduration_s: 1\n")
    cfg = load_config(cfg_path, overrides=["progress=false", "camera.encoding=raw",
                                           f'target.command=["{fresh_python}", "-I", "{prog}"]'])
    result = execute(cfg, out_dir=prepare_out_dir(tmp_path / "r"), gl_backend=GL_BACKEND,
                     install_signal_handlers=False)
    v = result.summary["vehicles"]["ego0"]
    assert result.summary["ended_by"] == "duration"
    assert v["target"]["name"] == "wheel-device"
    assert v["frames_sent"] == 20 and v["estimates_applied"] >= 18, v
    assert v["clock"]["synced"]


@pytest.mark.slow
def test_the_harness_wheel_depends_on_the_sdk_and_carries_no_copy(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                    "-w", str(tmp_path), str(ROOT)], check=True, capture_output=True, timeout=300)
    wheel = next(tmp_path.glob("hil_harness-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        meta = z.read(next(n for n in names if n.endswith("/METADATA"))).decode()
    tops = {"/".join(n.split("/")[:2]) for n in names if n.startswith("hil/")}
    assert tops == {"hil/harness", "hil/scenarios", "hil/targets", "hil/training"}, tops
    assert "hil/targets/weights/detector.pt" in names
    assert "Requires-Dist: hil-target-sdk==0.1.0" in meta.splitlines()
