"""A vehicle's camera rig on the wire (PROTOCOL.md 4.2.1): which rendered frames go
to its target, and their frame ids.

The render workers hand over each camera's frame on its own (``FrameReady.camera``),
in camera order within an instant. A rig of several cameras goes to a target whose
HELLO set ``CAP_CAMERAS`` as **frame sets**: the frames of one trigger instant carry
consecutive frame ids in camera order (camera k: set id + k), the set's ``sim_time``
(its camera 0's trigger instant; a camera with a trigger offset shows its own
instant, ``t_state`` says when) and ``camera_count``. A camera whose frame never
comes leaves its frame id unused. Any other target gets camera 0 only, as a single
camera (``camera_count`` 0), and the run says so once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hil.adapters.frame_sets import CameraMode
from hil.adapters.wire import protocol
from hil.adapters.wire.messages import CameraInfo


def target_mode(capabilities: int) -> CameraMode:
    """How a target takes a rig, from its HELLO's capability bits (bit 4 without bit
    3 means neither: PROTOCOL.md 4.2.1)."""
    if not capabilities & protocol.CAP_CAMERAS:
        return CameraMode.ONE
    return CameraMode.SET if capabilities & protocol.CAP_FRAME_SETS else CameraMode.EACH


@dataclass(frozen=True)
class RigCam:
    """What a camera's frames carry: its calibration, image size and name."""

    name: str
    info: CameraInfo
    width: int
    height: int


def rig_cams(sim: Any) -> tuple[RigCam, ...]:
    """Each camera of the egos' rig as its frames carry it (``sim``: a
    ``hil.scenarios.sim.Simulation`` of the run's world)."""
    out = []
    for k, m in enumerate(sim.mounts):
        intr = sim.intrinsics(k)
        out.append(RigCam(m.name, CameraInfo(intr.fx, intr.fy, intr.cx, intr.cy, m.height_m, m.pitch_rad),
                          m.width, m.height))
    return tuple(out)


@dataclass(frozen=True)
class Numbered:
    """A frame's place on the wire: its id, the sim time (ns) it carries, and its
    camera index and count (0, 0: a single camera)."""

    frame_id: int
    sim_time_ns: int
    camera_index: int
    camera_count: int


class RigNumbering:
    """Frame ids of one vehicle's frames (see the module docstring). ``offsets``:
    each camera's trigger after camera 0, in physics steps; ``step_ns``: the
    physics step."""

    def __init__(self, offsets: tuple[int, ...], step_ns: int) -> None:
        self.offsets, self.step_ns = offsets, step_ns
        self.mode: CameraMode | None = None  # the target's, once known
        self._set_steps = -1
        self._set_id = 0

    @property
    def cameras(self) -> int:
        return len(self.offsets)

    def sends_sets(self) -> bool:
        return self.cameras > 1 and self.mode not in (None, CameraMode.ONE)

    def answers_sets(self) -> bool:
        """The target answers one ESTIMATE per frame set (``CAP_FRAME_SETS``)."""
        return self.sends_sets() and self.mode == CameraMode.SET

    def number(self, next_frame_id: int, steps: int, camera: int) -> tuple[Numbered | None, int]:
        """The place of camera ``camera``'s frame captured at step ``steps`` (None: not
        sent to this target), and the vehicle's next unused frame id."""
        if not self.sends_sets():
            if camera:
                return None, next_frame_id
            return Numbered(next_frame_id, steps * self.step_ns, 0, 0), next_frame_id + 1
        set_steps = steps - self.offsets[camera]
        if set_steps < self._set_steps:  # a set already left behind (never: a worker renders in order)
            return None, next_frame_id
        if set_steps != self._set_steps:  # a later instant: a new set
            self._set_steps, self._set_id = set_steps, next_frame_id
            next_frame_id += self.cameras
        return Numbered(self._set_id + camera, set_steps * self.step_ns, camera, self.cameras), next_frame_id


__all__ = ["Numbered", "RigCam", "RigNumbering", "rig_cams", "target_mode"]
