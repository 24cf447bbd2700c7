"""A minimal target: answers every frame with a fixed control, after an optional
busy inference time. It is the floor for transport benchmarks and the known-latency
target of timing tests (it never looks at the image).

    python -m hil.targets.echo --infer-ms 20 --throttle 0.1
    python -m hil.targets.echo --cameras set     # a fusing stack: one ESTIMATE per frame set

With ``--cameras set`` it answers each frame set with one object per camera that came
(UNKNOWN, its ``camera`` the camera's index), SLOW when a camera is missing, else SAFE:
what the SDK handed it, on the wire for tests of rigs. ``--object CLS:X:Y[:CAMERA]``
(repeatable) reports those objects in every answer instead (vehicle frame, m; a fixed
belief for tests of the corner-case detector):

    python -m hil.targets.echo --cameras set --object vehicle:-7.05:2.8:3
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence

from typing import TYPE_CHECKING

from hil.adapters.wire.messages import Control, DetectedObject, DrivingState, Frame, Inference, ObjectClass
from hil.timing.clock import Clock, MonotonicClock, OffsetClock

if TYPE_CHECKING:
    from hil.adapters.frame_sets import FrameSet


class Echo:
    """``infer`` spins for ``infer_ms`` (wall clock; spinning, not sleeping, so the
    duration is exact) then returns SAFE with the given control."""

    def __init__(self, *, infer_ms: float = 0.0, throttle: float = 0.0, brake: float = 0.0,
                 exit_after_frames: int | None = None, camera_delay: tuple[int, float] | None = None,
                 objects: tuple[DetectedObject, ...] = ()) -> None:
        """``camera_delay``: (camera index, ms) spent more on that camera's frames;
        ``objects``: reported in every answer."""
        self.infer_ns = int(infer_ms * 1e6)
        self.camera_delay = None if camera_delay is None else (camera_delay[0], int(camera_delay[1] * 1e6))
        self.objects = objects
        self.result = Inference(DrivingState.SAFE, Control(0.0, throttle, brake), objects)
        self.exit_after_frames = exit_after_frames
        self.frames = 0

    def infer_set(self, frames: FrameSet) -> Inference:
        """A frame set: one object per camera that came, SLOW when one is missing."""
        result = self.infer(frames.frames[-1])
        seen = self.objects or tuple(DetectedObject(ObjectClass.UNKNOWN, 1.0, (0.0, 0.0, 1.0, 1.0), (0.0, 0.0, 0.0),
                                                    f.camera_index) for f in frames.frames)
        return Inference(DrivingState.SAFE if frames.complete else DrivingState.SLOW, result.control, seen)

    def infer(self, frame: Frame) -> Inference:
        self.frames += 1
        if self.exit_after_frames is not None and self.frames > self.exit_after_frames:
            # Die abruptly, like a crashed device: no BYE, no flush.
            os._exit(3)
        busy = self.infer_ns
        if self.camera_delay is not None and frame.camera_index == self.camera_delay[0]:
            busy += self.camera_delay[1]
        if busy:
            end = time.monotonic_ns() + busy
            while time.monotonic_ns() < end:
                pass
        return self.result


class _AbsurdClock:
    """A broken target clock, for tests of what the harness does with absurd
    timestamps: ``zero`` always reads 0, ``future`` jumps ~12 days ahead on every
    7th reading (a constant far offset would only be another epoch), and
    ``backwards`` runs backwards."""

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self._start = time.monotonic_ns()
        self._reads = 0

    def now_ns(self) -> int:
        now = time.monotonic_ns()
        self._reads += 1
        if self.mode == "zero":
            return 0
        if self.mode == "future":
            return now + 10**15 if self._reads % 7 == 0 else now
        return self._start - (now - self._start)


def _clock(a: argparse.Namespace) -> Clock:
    if a.bad_stamps:
        return _AbsurdClock(a.bad_stamps)
    if a.clock_offset_s or a.clock_skew_ppm:
        return OffsetClock(MonotonicClock(), offset_ns=int(a.clock_offset_s * 1e9), skew_ppm=a.clock_skew_ppm)
    return MonotonicClock()


def _camera_delay(text: str) -> tuple[int, float]:
    index, sep, ms = text.partition(":")
    try:
        k, d = int(index), float(ms)
    except ValueError:
        k, d = -1, -1.0
    if not sep or not 0 <= k < 32 or not 0 <= d <= 60_000:
        raise argparse.ArgumentTypeError(f"{text!r}: INDEX:MS, a camera 0..31 and 0..60000 ms, e.g. 5:30")
    return k, d


def _object(text: str) -> DetectedObject:
    parts = text.split(":")
    try:
        cls = ObjectClass[parts[0].upper()]
        x, y = float(parts[1]), float(parts[2])
        camera = int(parts[3]) if len(parts) == 4 else 0
    except (KeyError, IndexError, ValueError):
        cls, x, y, camera = ObjectClass.UNKNOWN, 0.0, 0.0, -1
    if not 3 <= len(parts) <= 4 or not 0 <= camera < 32:
        names = ", ".join(c.label for c in ObjectClass)
        raise argparse.ArgumentTypeError(f"{text!r}: CLS:X:Y[:CAMERA], a class ({names}), metres and a camera "
                                         "0..31, e.g. vehicle:12.5:-0.4")
    return DetectedObject(cls, 1.0, (0.0, 0.0, 1.0, 1.0), (x, y, 0.0), camera)


def main(argv: Sequence[str] | None = None, *, prog: str = "python -m hil.targets.echo") -> int:
    from hil.adapters.sdk import TargetArgumentParser, add_transport_args, run_target, serve, transport_options

    p = TargetArgumentParser(prog=prog, description=" ".join(__doc__.split("\n\n")[0].split()))  # the first paragraph
    p.add_argument("--infer-ms", type=float, default=0.0, help="busy time per frame (ms)")
    p.add_argument("--throttle", type=float, default=0.0)
    p.add_argument("--brake", type=float, default=0.0)
    p.add_argument("--name", default="echo")
    p.add_argument("--exit-after-frames", type=int, default=None,
                   help="crash (exit 3) on the frame after this many: for failure tests")
    p.add_argument("--clock-offset-s", type=float, default=0.0,
                   help="stamp with a clock this far ahead of the host's (s): a target on another clock")
    p.add_argument("--clock-skew-ppm", type=float, default=0.0, help="... running this much fast (ppm)")
    p.add_argument("--bad-stamps", choices=("zero", "future", "backwards"), default=None,
                   help="stamp with a broken clock: for tests of absurd timestamps")
    p.add_argument("--cameras", choices=("one", "each", "set"), default="one",
                   help="a camera rig: one ESTIMATE per camera (each) or per frame set (set); one: a single camera")
    p.add_argument("--set-timeout-ms", type=float, default=100.0,
                   help="--cameras set: give up an incomplete frame set this long after its first frame (ms)")
    p.add_argument("--camera-delay-ms", type=_camera_delay, default=None, metavar="INDEX:MS",
                   help="spend MS more on camera INDEX's frames: a rig with one slow camera, for tests")
    p.add_argument("--object", type=_object, action="append", default=[], metavar="CLS:X:Y[:CAMERA]",
                   help="report this object (vehicle frame, m; its box in CAMERA) in every answer; repeatable")
    add_transport_args(p)
    a = p.parse_args(argv)
    echo = Echo(infer_ms=a.infer_ms, throttle=a.throttle, brake=a.brake, exit_after_frames=a.exit_after_frames,
                camera_delay=a.camera_delay_ms, objects=tuple(a.object))
    sets = a.cameras == "set"
    return run_target(prog, lambda: serve(None if sets else echo.infer, target_name=a.name, transport=a.transport,
                                          clock=_clock(a), cameras=a.cameras, infer_set=echo.infer_set if sets else None,
                                          set_timeout_s=a.set_timeout_ms / 1e3, **transport_options(a)))


if __name__ == "__main__":
    raise SystemExit(main())
