"""Targets that take a vehicle's camera rig (PROTOCOL.md 4.2): the frames of one
capture instant form a **frame set** (consecutive ``frame_id``s in camera order, one
``sim_time``); a target answers one ESTIMATE per camera (``CameraMode.EACH``) or, a
fusing stack, one per set (``CameraMode.SET``)::

    from hil.adapters.sdk import serve

    def fuse(frames):                      # a FrameSet
        for f in frames.frames: ...        # the cameras that came, in camera order
        if frames.missing: ...             # cameras given up on (a later set began, or timed out)
        return Inference(DrivingState.SAFE, Control(throttle=0.2))

    serve(infer_set=fuse, target_name="fusing-ai")

``RigQueue`` is the endpoint's pending work for either mode (``hil.adapters.sdk``
holds its lock): newest first, as for one camera, but per camera (EACH) or per whole
set (SET), so a slow AI skips whole instants, never the same cameras every time.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum

from hil.adapters.wire import protocol
from hil.adapters.wire.cameras import CAMERA_COUNT_OFFSET, CAMERA_INDEX_OFFSET
from hil.adapters.wire.messages import Frame, Inference
from hil.common.errors import ConfigError, ProtocolError

SET_TIMEOUT_S = 0.1  # a set still incomplete this long after its first frame is given up


class CameraMode(Enum):
    """How a target takes a rig's cameras; its HELLO says so (``capabilities``)."""

    ONE = "one"  # a single-camera target: announces nothing, as every target before rigs
    EACH = "each"  # CAP_CAMERAS: one ESTIMATE per FRAME, for every camera of a set
    SET = "set"  # CAP_CAMERAS | CAP_FRAME_SETS: one ESTIMATE per frame set (a fusing stack)

    @property
    def capabilities(self) -> int:
        return {CameraMode.ONE: 0, CameraMode.EACH: protocol.CAP_CAMERAS,
                CameraMode.SET: protocol.CAP_CAMERAS | protocol.CAP_FRAME_SETS}[self]


@dataclass(frozen=True)
class FrameSet:
    """The frames of one capture instant, handed to a fusing target's ``infer_set``.

    ``set_id`` is the ``frame_id`` of its camera 0, which the ESTIMATE answers;
    ``camera_count`` 1 for a single camera's frame. ``frames``: those that came, in
    camera order; ``missing``: the cameras that did not, and ``given_up`` why (a later
    set began, or ``SET_TIMEOUT_S`` passed). ``t_rx_ns``: the receipt of its last frame
    to arrive (target clock), the ESTIMATE's ``t_rx``.
    """

    set_id: int
    camera_count: int
    frames: tuple[Frame, ...]
    t_rx_ns: int
    missing: tuple[int, ...] = ()
    given_up: str = ""

    @property
    def vehicle_id(self) -> int:
        return self.frames[0].vehicle_id

    @property
    def complete(self) -> bool:
        return not self.missing

    def camera(self, index: int) -> Frame | None:
        """Camera ``index``'s frame, None when it is missing."""
        return next((f for f in self.frames if f.camera_index == index), None)


SetInferFn = Callable[[FrameSet], Inference]


def on_camera(result: Inference, frame: Frame) -> Inference:
    """``result`` as the ESTIMATE of one FRAME: its objects name the frame's camera
    (PROTOCOL.md 4.3, byte +1), whatever the AI put there."""
    if all(o.camera == frame.camera_index for o in result.objects):
        return result
    return replace(result, objects=tuple(replace(o, camera=frame.camera_index) for o in result.objects))


def camera_mode(infer: object, cameras: CameraMode | str | None, infer_set: object) -> CameraMode:
    """The mode of a target given ``infer``, ``cameras`` and ``infer_set``: SET with
    ``infer_set``, else ONE unless ``cameras`` says EACH.

    Raises:
        ConfigError: a mode without the function it calls, or an unknown name.
    """
    try:
        mode = CameraMode(cameras) if cameras is not None else CameraMode.SET if infer_set else CameraMode.ONE
    except ValueError:
        raise ConfigError(f"cameras={cameras!r}: expected one of "
                          f"{', '.join(m.value for m in CameraMode)}") from None
    if (mode is CameraMode.SET) != (infer_set is not None):
        raise ConfigError("cameras='set' takes infer_set (called with each FrameSet), and only it")
    if mode is not CameraMode.SET and infer is None:
        raise ConfigError(f"cameras={mode.value!r} needs infer (called with each Frame)")
    return mode


@dataclass
class _Partial:
    set_id: int
    count: int
    sim_time_ns: int
    deadline_s: float
    got: dict[int, tuple[Frame, int]] = field(default_factory=dict)

    def done(self, why: str = "") -> FrameSet:
        frames = tuple(self.got[i][0] for i in sorted(self.got))
        missing = tuple(i for i in range(self.count) if i not in self.got)
        return FrameSet(self.set_id, self.count, frames, max(t for _, t in self.got.values()), missing,
                        why if missing else "")


class RigQueue:
    """A multi-camera endpoint's pending work: ``put`` each FRAME as it arrives,
    ``take`` the next item for the AI (a ``(Frame, t_rx)`` in EACH mode, a
    ``FrameSet`` in SET mode). Times ``now_s`` are seconds of a monotonic clock. Not
    thread-safe: the endpoint holds its lock around every call."""

    def __init__(self, mode: CameraMode, *, timeout_s: float = SET_TIMEOUT_S) -> None:
        if timeout_s <= 0:
            raise ConfigError(f"set_timeout_s={timeout_s}: must be > 0")
        self.mode = mode
        self.timeout_s = timeout_s
        self._each: OrderedDict[int, tuple[Frame, int]] = OrderedDict()
        self._partial: _Partial | None = None
        self._ready: FrameSet | None = None
        self._last_set: int | None = None  # id of the newest set finished

    def put(self, frame: Frame, t_rx: int, now_s: float) -> tuple[int, ProtocolError | None]:
        """Add a frame; returns (frames now skipped, the error to report for a frame
        that contradicts its set: it is dropped)."""
        if self.mode is CameraMode.EACH:
            skipped = int(self._each.pop(frame.camera_index, None) is not None)
            self._each[frame.camera_index] = (frame, t_rx)
            return skipped, None
        skipped = self._expire(now_s)
        p, sid = self._partial, frame.set_id
        if (self._last_set is not None and sid <= self._last_set) or (p is not None and sid < p.set_id):
            return skipped + 1, None  # its set is over (given up or answered): too late
        if p is not None and sid > p.set_id:
            skipped += self._finish(p.done(f"set {sid} began"))
            p = None
        if p is None:
            p = self._partial = _Partial(sid, max(frame.camera_count, 1), frame.sim_time_ns, now_s + self.timeout_s)
        if (error := self._contradiction(p, frame)) is not None:
            return skipped, error
        p.got[frame.camera_index] = (frame, t_rx)
        if len(p.got) == p.count:
            skipped += self._finish(p.done())
        return skipped, None

    @staticmethod
    def _contradiction(p: _Partial, f: Frame) -> ProtocolError | None:
        if max(f.camera_count, 1) != p.count:
            return ProtocolError(f"camera_count {f.camera_count} in set {p.set_id}, whose first frame said "
                                 f"{p.count}", offset=CAMERA_COUNT_OFFSET)
        if f.camera_index in p.got:
            return ProtocolError(f"camera {f.camera_index} of set {p.set_id} came twice (frame_id {f.frame_id})",
                                 offset=CAMERA_INDEX_OFFSET)
        if f.sim_time_ns != p.sim_time_ns:
            return ProtocolError(f"sim_time {f.sim_time_ns} ns in set {p.set_id}, whose first frame said "
                                 f"{p.sim_time_ns}: one capture instant has one sim_time", offset=32)
        return None

    def _finish(self, s: FrameSet) -> int:
        """``s`` is ready for the AI; returns the frames of the set it replaces (skipped)."""
        replaced = len(self._ready.frames) if self._ready is not None else 0
        self._ready, self._partial, self._last_set = s, None, s.set_id
        return replaced

    def _expire(self, now_s: float) -> int:
        p = self._partial
        if p is not None and now_s >= p.deadline_s:
            return self._finish(p.done(f"timed out after {self.timeout_s:g} s"))
        return 0

    def take(self, now_s: float) -> tuple[Frame, int] | FrameSet | None:
        """The next item for the AI, or None (then wait at most ``wait_s``)."""
        if self.mode is CameraMode.EACH:
            return self._each.popitem(last=False)[1] if self._each else None
        if self._ready is None:
            self._expire(now_s)  # nothing ready: nothing replaced
        item, self._ready = self._ready, None
        return item

    def wait_s(self, now_s: float) -> float | None:
        """Seconds until the incomplete set is given up; None: nothing to wait for."""
        return None if self._partial is None else max(0.0, self._partial.deadline_s - now_s)


__all__ = ["SET_TIMEOUT_S", "CameraMode", "FrameSet", "RigQueue", "SetInferFn", "camera_mode", "on_camera"]
