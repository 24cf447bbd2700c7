"""The MuJoCo simulation of a world: physics, actuators, cameras, ground truth.

Call ``scenarios.gl.select_backend()`` before this module is imported (it imports
``mujoco``, which fixes its OpenGL backend at import).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from scenarios.ground_truth import Collision, EgoTruth, EntityState, GroundTruth, RefStateRules
from scenarios.vehicle import VehicleLimits, VehicleState, step_command
from scenarios.world import VehicleSpec, WorldSpec, build_mjcf, camera_name
from timing.errors import SimulationError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a MuJoCo camera image (pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float


class Simulation:
    """Owns the MuJoCo model, data and renderer of one world. A context manager;
    ``close()`` is idempotent and safe on a half-built object.

    Raises:
        SimulationError: the world does not compile or the renderer cannot start.
    """

    def __init__(self, world: WorldSpec, *, limits: VehicleLimits | None = None,
                 rules: RefStateRules | None = None) -> None:
        self._renderer: mujoco.Renderer | None = None
        self.world = world
        self.limits = limits or VehicleLimits()
        self.rules = rules or RefStateRules()
        try:
            self.model = mujoco.MjModel.from_xml_string(build_mjcf(world))
        except ValueError as err:
            raise SimulationError(f"scenario world does not compile: {err}") from err
        self.data = mujoco.MjData(self.model)
        self.step_ns = round(world.physics_step_s * 1e9)
        self.steps = 0
        self.egos: tuple[str, ...] = tuple(v.name for v in world.vehicles if v.ego)
        self._specs: dict[str, VehicleSpec] = {v.name: v for v in world.vehicles}
        self._state: dict[str, VehicleState] = {}
        self._qpos: dict[str, int] = {}
        self._dof: dict[str, int] = {}
        self._act: dict[str, int] = {}
        for name in self.egos:
            jx = self.model.joint(f"{name}/x")
            self._qpos[name] = int(jx.qposadr[0])
            self._dof[name] = int(jx.dofadr[0])
            self._act[name] = int(self.model.actuator(f"{name}/x").id)
            self._state[name] = VehicleState(speed_mps=self._specs[name].speed_mps)
        self._body_of_geom = {
            int(g): self.model.body(int(self.model.geom_bodyid[g])).name for g in range(self.model.ngeom)
        }
        self._active_contacts: set[tuple[str, str]] = set()
        self._new_collisions: list[Collision] = []
        self._set_initial_velocities()
        mujoco.mj_forward(self.model, self.data)

    # -- physics -------------------------------------------------------------

    @property
    def sim_time_ns(self) -> int:
        return self.steps * self.step_ns

    def _set_initial_velocities(self) -> None:
        for name in self.egos:
            v = self._state[name].speed_mps
            yaw = self._specs[name].yaw_rad
            dof = self._dof[name]
            self.data.qvel[dof:dof + 2] = (v * math.cos(yaw), v * math.sin(yaw))

    def set_control(self, vehicle: str, *, steering_rad: float, throttle: float, brake: float) -> None:
        """Set the actuator commands of an ego vehicle (applied from the next step)."""
        st = self._state[vehicle]
        st.cmd_steer_rad, st.cmd_throttle, st.cmd_brake = steering_rad, throttle, brake

    def pose(self, vehicle: str) -> tuple[float, float, float]:
        """(x m, y m, yaw rad) of a vehicle in the world."""
        if vehicle in self._qpos:
            a = self._qpos[vehicle]
            spec = self._specs[vehicle]
            return (spec.x_m + float(self.data.qpos[a]), spec.y_m + float(self.data.qpos[a + 1]),
                    spec.yaw_rad + float(self.data.qpos[a + 2]))
        spec = self._specs[vehicle]
        return spec.x_m, spec.y_m, spec.yaw_rad

    def speed_mps(self, vehicle: str) -> float:
        """Forward speed (m/s) as the simulator has it."""
        if vehicle not in self._dof:
            return 0.0
        d = self._dof[vehicle]
        yaw = self.pose(vehicle)[2]
        return float(self.data.qvel[d] * math.cos(yaw) + self.data.qvel[d + 1] * math.sin(yaw))

    def step(self) -> None:
        """Advance physics by one step (``world.physics_step_s``)."""
        dt = self.world.physics_step_s
        for name in self.egos:
            speed, yaw_rate = step_command(self._state[name], self.limits,
                                           measured_speed_mps=self.speed_mps(name), dt_s=dt)
            yaw = self.pose(name)[2]
            a = self._act[name]
            self.data.ctrl[a:a + 3] = (speed * math.cos(yaw), speed * math.sin(yaw), yaw_rate)
        mujoco.mj_step(self.model, self.data)
        self.steps += 1
        self._scan_contacts()

    def _scan_contacts(self) -> None:
        now: set[tuple[str, str]] = set()
        force = np.zeros(6)
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            a = self._body_of_geom[int(c.geom1)]
            b = self._body_of_geom[int(c.geom2)]
            if a == b or a == "world" or b == "world":
                continue
            pair = (a, b) if a < b else (b, a)
            if pair not in self._active_contacts and pair not in now:
                mujoco.mj_contactForce(self.model, self.data, i, force)
                self._new_collisions.append(Collision(self.sim_time_ns, pair[0], pair[1], float(abs(force[0]))))
            now.add(pair)
        self._active_contacts = now

    # -- cameras -------------------------------------------------------------

    def intrinsics(self) -> Intrinsics:
        cam = self.world.camera
        fy = (cam.height / 2) / math.tan(math.radians(cam.fovy_deg) / 2)
        return Intrinsics(fx=fy, fy=fy, cx=cam.width / 2, cy=cam.height / 2)

    def open_renderer(self) -> None:
        cam = self.world.camera
        try:
            self._renderer = mujoco.Renderer(self.model, cam.height, cam.width)
        except Exception as err:  # mujoco raises bare RuntimeError/ImportError here
            raise SimulationError(f"cannot start the MuJoCo renderer: {err}") from err
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.world.shadows
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = self.world.reflections
        self._buffers = {n: np.empty((cam.height, cam.width, 3), np.uint8) for n in self.egos}

    def render(self, vehicle: str) -> np.ndarray:
        """RGB8 image (height x width x 3) of ``vehicle``'s camera; the array is
        reused by the next render of the same camera."""
        if self._renderer is None:
            self.open_renderer()
        assert self._renderer is not None
        self._renderer.update_scene(self.data, camera=camera_name(vehicle))
        return self._renderer.render(out=self._buffers[vehicle])

    # -- ground truth --------------------------------------------------------

    def ground_truth(self) -> GroundTruth:
        ents = []
        for v in self.world.vehicles:
            x, y, yaw = self.pose(v.name)
            if v.name in self._dof:
                d = self._dof[v.name]
                vx, vy = float(self.data.qvel[d]), float(self.data.qvel[d + 1])
            else:
                vx = vy = 0.0
            ents.append(EntityState(v.name, "vehicle", x, y, vx, vy, yaw, v.size_m))
        egos = tuple(self._ego_truth(name) for name in self.egos)
        collisions, self._new_collisions = tuple(self._new_collisions), []
        return GroundTruth(self.sim_time_ns, tuple(ents), egos, collisions)

    def _ego_truth(self, name: str) -> EgoTruth:
        ex, ey, eyaw = self.pose(name)
        spec = self._specs[name]
        c, s = math.cos(eyaw), math.sin(eyaw)
        best: tuple[float, str] | None = None
        for other in self.world.vehicles:
            if other.name == name:
                continue
            ox, oy, _ = self.pose(other.name)
            fwd = (ox - ex) * c + (oy - ey) * s
            lat = -(ox - ex) * s + (oy - ey) * c
            if fwd <= 0 or abs(lat) > (spec.size_m[1] + other.size_m[1]) / 2:
                continue
            gap = fwd - spec.size_m[0] / 2 - other.size_m[0] / 2
            if best is None or gap < best[0]:
                best = (gap, other.name)
        speed = self.speed_mps(name)
        gap_m = max(0.0, best[0]) if best else None
        return EgoTruth(name, gap_m, best[1] if best else None, speed,
                        self.rules.decide(gap_m=gap_m, speed_mps=speed))

    # -- lifetime ------------------------------------------------------------

    def close(self) -> None:
        r = getattr(self, "_renderer", None)
        if r is not None:
            self._renderer = None
            r.close()

    def __enter__(self) -> Simulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
