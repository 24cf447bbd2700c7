"""The MuJoCo simulation of a world: physics, actuators, scripted motion, cameras,
ground truth.

Each physics step: scripted entities (mocap bodies) are placed at their script's
pose for the step's start time, every ego's actuators advance (``VehicleBank``),
MuJoCo steps, and new contacts between entities become ``Collision`` records. At a
camera tick the kinematics are brought up to the current instant (``mj_kinematics``
after the step leaves them one step behind), so images and ground truth show the
same sim time.

Call ``hil.scenarios.gl.select_backend()`` before this module is imported (it imports
``mujoco``, which fixes its OpenGL backend at import).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from hil.scenarios.ground_truth import (
                                        CameraTruth,
                                        Collision,
                                        EgoTruth,
                                        EntityTable,
                                        GroundTruth,
                                        RefStateRules,
                                        VisibleBox,
                                        )
from hil.common.errors import SimulationError
from hil.scenarios.motion import ScriptTable
from hil.scenarios.path import Path
from hil.scenarios.render import SceneRenderer
from hil.scenarios.vehicle import EgoActuators, VehicleLimits, VehicleState
from hil.scenarios.visibility import pixel_boxes, silhouette_area
from hil.scenarios.world import VehicleSpec, WorldSpec, build_mjcf, camera_name


# (x, y, heading, vx, vy) of every entity: metres, radians, m/s.
_States = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


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
        self._renderer: SceneRenderer | None = None
        self.world = world
        self.limits = limits or VehicleLimits()
        self.rules = rules or RefStateRules()
        try:
            self.model = mujoco.MjModel.from_xml_string(build_mjcf(world))
        except ValueError as err:
            raise SimulationError(f"scenario world does not compile: {err}") from err
        m = self.model
        self.data = mujoco.MjData(m)
        self.step_ns = round(world.physics_step_s * 1e9)
        self.steps = 0
        self._specs: dict[str, VehicleSpec] = {v.name: v for v in world.vehicles}
        self._entity_index = {v.name: i for i, v in enumerate(world.vehicles)}
        self.egos: tuple[str, ...] = tuple(v.name for v in world.vehicles if v.ego)
        self._ego_index = {name: i for i, name in enumerate(self.egos)}
        qx = [int(m.joint(f"{n}/x").qposadr[0]) for n in self.egos]
        dx = [int(m.joint(f"{n}/x").dofadr[0]) for n in self.egos]
        ax = [int(m.actuator(f"{n}/x").id) for n in self.egos]
        self._qx, self._qy, self._qyaw = (np.array(qx, int), np.array(qx, int) + 1, np.array(qx, int) + 2)
        self._dx, self._dy = np.array(dx, int), np.array(dx, int) + 1
        self._ax, self._ay, self._ayaw = (np.array(ax, int), np.array(ax, int) + 1, np.array(ax, int) + 2)
        self._x0 = np.array([self._specs[n].x_m for n in self.egos])
        self._y0 = np.array([self._specs[n].y_m for n in self.egos])
        self._routes = {n: self._specs[n].route_path() for n in self.egos}
        scripted = [v for v in world.vehicles if v.script is not None]
        self._scripted = {v.name: j for j, v in enumerate(scripted)}
        self._mocap = np.array([int(m.body_mocapid[m.body(v.name).id]) for v in scripted], int)
        self._table = ScriptTable([v.script for v in scripted], self.step_ns)
        self._body_entity = np.full(m.nbody, -1, np.int32)
        for v in world.vehicles:
            self._body_entity[m.body(v.name).id] = self._entity_index[v.name]
        self._geom_entity = self._body_entity[m.geom_bodyid]
        self._entity_geoms: list[list[int]] = [[] for _ in world.vehicles]
        for g in range(m.ngeom):
            if self._geom_entity[g] >= 0:
                self._entity_geoms[int(self._geom_entity[g])].append(g)
        self.mounts = world.camera.mounts()  # the cameras of every ego, camera 0 first
        self._cam_ids = {n: [int(m.camera(camera_name(n, k)).id) for k in range(len(self.mounts))]
                         for n in self.egos}
        self._active_contacts: set[tuple[str, str]] = set()
        self._new_collisions: list[Collision] = []
        self._kin_step = -1
        n = len(world.vehicles)
        self._actuators = EgoActuators(self.limits, [self._specs[e].speed_mps for e in self.egos],
                                       qpos=self.data.qpos, qvel=self.data.qvel, ctrl=self.data.ctrl,
                                       qpos_x=qx, dof_x=dx, act_x=ax)
        self._ego_ids = np.array([self._entity_index[e] for e in self.egos], int)
        self._scripted_ids = np.array([self._entity_index[v.name] for v in scripted], int)
        self._static_states = np.array([[v.x_m, v.y_m, v.yaw_rad, 0.0, 0.0] for v in world.vehicles],
                                       float).T.copy() if n else np.zeros((5, 0))
        self._half_l = np.array([v.size_m[0] / 2 for v in world.vehicles])
        self._half_w = np.array([v.size_m[1] / 2 for v in world.vehicles])
        self._others = [np.array([j for j in range(n) if j != i], int) for i in range(n)]
        # Each entity's fixed part of its EntityState (name, class label, size, id), read
        # at every camera instant: the label's enum lookup was a third of ground_truth().
        self._names = tuple(v.name for v in world.vehicles)
        self._classes = tuple(v.cls.label for v in world.vehicles)
        self._sizes = tuple(v.size_m for v in world.vehicles)
        self._dims = np.array(self._sizes, float).reshape(n, 3)
        self._ids = tuple(range(n))
        self._states_step = -1
        self._states_cache: _States | None = None
        self._states_arr = np.zeros((5, 0))  # the cache's rows as one (5, n) array
        self._qvel_before = np.zeros(m.nv)
        self._rgb: dict[tuple[str, int], np.ndarray] = {}
        self._seg: dict[tuple[int, int], np.ndarray] = {}  # segmentation buffers by image size
        for i, name in enumerate(self.egos):  # start headings and speeds
            yaw = self._specs[name].yaw_rad
            self.data.qpos[self._qyaw[i]] = yaw
            speed = self._specs[name].speed_mps
            self.data.qvel[self._dx[i]], self.data.qvel[self._dy[i]] = speed * math.cos(yaw), speed * math.sin(yaw)
        self._place_scripted(0)
        mujoco.mj_forward(m, self.data)
        self._kin_step = 0

    # -- physics -------------------------------------------------------------

    @property
    def sim_time_ns(self) -> int:
        return self.steps * self.step_ns

    def set_control(self, vehicle: str, *, steering_rad: float, throttle: float, brake: float) -> None:
        """Set the actuator commands of an ego vehicle (applied from the next step)."""
        self._actuators.set_command(self._ego_index[vehicle], steering_rad=steering_rad, throttle=throttle,
                                    brake=brake)

    def vehicle_state(self, vehicle: str) -> VehicleState:
        """An ego's actuator state (speed set point, steering angle, commands)."""
        return self._actuators.state(self._ego_index[vehicle])

    def set_pose(self, vehicle: str, *, x_m: float, y_m: float, yaw_rad: float) -> None:
        """Move an ego vehicle (for tests and set-ups); its speed is kept."""
        i = self._ego_index[vehicle]
        q = self.data.qpos
        q[self._qx[i]], q[self._qy[i]], q[self._qyaw[i]] = x_m - self._x0[i], y_m - self._y0[i], yaw_rad
        mujoco.mj_forward(self.model, self.data)
        self._states_step = -1

    def route(self, vehicle: str) -> Path:
        """The path an ego means to follow (its lane): ground truth measures along it."""
        return self._routes[vehicle]

    def pose(self, vehicle: str) -> tuple[float, float, float]:
        """(x m, y m, yaw rad) of an entity in the world."""
        i = self._ego_index.get(vehicle)
        if i is not None:
            q = self.data.qpos
            return (float(self._x0[i] + q[self._qx[i]]), float(self._y0[i] + q[self._qy[i]]),
                    float(q[self._qyaw[i]]))
        j = self._scripted.get(vehicle)
        if j is not None:
            r = self._table.row(self.steps)
            qw, qz = self._table.quat[r, j, 0], self._table.quat[r, j, 3]
            return (float(self._table.pos[r, j, 0]), float(self._table.pos[r, j, 1]),
                    float(2 * math.atan2(qz, qw)))
        spec = self._specs[vehicle]
        return spec.x_m, spec.y_m, spec.yaw_rad

    def velocity(self, vehicle: str) -> tuple[float, float]:
        """(vx, vy) m/s of an entity in the world."""
        i = self._ego_index.get(vehicle)
        if i is not None:
            return float(self.data.qvel[self._dx[i]]), float(self.data.qvel[self._dy[i]])
        j = self._scripted.get(vehicle)
        if j is not None:
            r = self._table.row(self.steps)
            return float(self._table.vel[r, j, 0]), float(self._table.vel[r, j, 1])
        return 0.0, 0.0

    def _velocity_before(self, vehicle: str) -> tuple[float, float]:
        """Velocity at the start of the step being taken (before contact impulses)."""
        i = self._ego_index.get(vehicle)
        if i is None:
            return self.velocity(vehicle)
        return float(self._qvel_before[self._dx[i]]), float(self._qvel_before[self._dy[i]])

    def speed_mps(self, vehicle: str) -> float:
        """Forward speed (m/s) as the simulator has it."""
        vx, vy = self.velocity(vehicle)
        yaw = self.pose(vehicle)[2]
        return vx * math.cos(yaw) + vy * math.sin(yaw)

    def step(self) -> None:
        """Advance physics by one step (``world.physics_step_s``)."""
        d = self.data
        if len(self._mocap):
            self._place_scripted(self.steps)
        self._actuators.step(self.world.physics_step_s)
        np.copyto(self._qvel_before, d.qvel)  # the speeds going into a contact
        mujoco.mj_step(self.model, d)
        if d.ncon or self._active_contacts:
            self._scan_contacts()
        self.steps += 1

    # -- state hand-over (physics process -> mirrors that render and judge) ----

    def state(self) -> tuple[int, np.ndarray, np.ndarray]:
        """(step count, qpos copy, qvel copy): everything a mirror of this world
        needs to show and judge the present instant (scripted entities follow from
        the step count)."""
        return self.steps, self.data.qpos.copy(), self.data.qvel.copy()

    def load_state(self, steps: int, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Make this simulation a mirror of another one's ``state()``: images, ground
        truth and camera truth then show that instant exactly."""
        self.steps = steps
        np.copyto(self.data.qpos, qpos)
        np.copyto(self.data.qvel, qvel)
        self._kin_step = -1
        self._states_step = -1

    def take_collisions(self) -> list[Collision]:
        """The collisions that began since the previous call (physics side)."""
        out, self._new_collisions = self._new_collisions, []
        return out

    def add_collisions(self, collisions: list[Collision]) -> None:
        """Collisions found by the physics this mirror follows; the next
        ``ground_truth()`` reports them."""
        self._new_collisions.extend(collisions)

    def _place_scripted(self, step: int) -> None:
        if len(self._mocap):
            r = self._table.row(step)
            self.data.mocap_pos[self._mocap] = self._table.pos[r]
            self.data.mocap_quat[self._mocap] = self._table.quat[r]

    def _sync_kinematics(self) -> None:
        """Bring body, geom and camera poses to the present step (rendering and truth)."""
        if self._kin_step != self.steps:
            self._place_scripted(self.steps)
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_camlight(self.model, self.data)
            self._kin_step = self.steps

    def _scan_contacts(self) -> None:
        now: set[tuple[str, str]] = set()
        names = [v.name for v in self.world.vehicles]
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            ea, eb = int(self._geom_entity[c.geom1]), int(self._geom_entity[c.geom2])
            if ea < 0 or eb < 0 or ea == eb:
                continue
            a, b = names[ea], names[eb]
            pair = (a, b) if a < b else (b, a)
            if pair not in self._active_contacts and pair not in now:
                force = np.zeros(6)
                mujoco.mj_contactForce(self.model, self.data, i, force)
                n = c.frame[:3]  # from geom1 towards geom2
                va, vb = self._velocity_before(a), self._velocity_before(b)
                into_a = va[0] * n[0] + va[1] * n[1]      # a moving towards b
                into_b = -(vb[0] * n[0] + vb[1] * n[1])   # b moving towards a
                striker = None
                if max(into_a, into_b) > 0.1:
                    striker = a if into_a >= into_b else b
                self._new_collisions.append(Collision(self.sim_time_ns, pair[0], pair[1], float(abs(force[0])),
                                                      round(float(into_a + into_b), 4), striker))
            now.add(pair)
        self._active_contacts = now

    # -- cameras -------------------------------------------------------------

    def intrinsics(self, camera: int = 0) -> Intrinsics:
        """Pinhole intrinsics (px) of camera ``camera`` of the egos' rig."""
        cam = self.mounts[camera]
        fy = (cam.height / 2) / math.tan(math.radians(cam.fovy_deg) / 2)
        return Intrinsics(fx=fy, fy=fy, cx=cam.width / 2, cy=cam.height / 2)

    def open_renderer(self) -> None:
        """Start the renderer (once; ``render`` starts it when needed).

        Raises:
            SimulationError: OpenGL cannot start.
        """
        if self._renderer is not None:
            return
        width, height = max(m.width for m in self.mounts), max(m.height for m in self.mounts)
        self._renderer = SceneRenderer(self.model, width=width, height=height, shadows=self.world.shadows,
                                       reflections=self.world.reflections, geom_entity=self._geom_entity)
        self._rgb = {(n, k): np.empty((m.height, m.width, 3), np.uint8) for n in self.egos
                     for k, m in enumerate(self.mounts)}
        self._seg = {(m.height, m.width): np.empty((m.height, m.width), np.int32) for m in self.mounts}

    def render(self, vehicle: str, camera: int = 0) -> np.ndarray:
        """RGB8 image (height x width x 3) of ``vehicle``'s camera ``camera`` (its
        rig's; 0: the first or only one); the array is reused by the next render of
        the same camera."""
        self.open_renderer()
        assert self._renderer is not None
        self._sync_kinematics()
        return self._renderer.rgb(self.data, self._cam_ids[vehicle][camera], self._rgb[(vehicle, camera)])

    def segmentation(self, vehicle: str, camera: int = 0) -> np.ndarray:
        """Entity id of each pixel of ``vehicle``'s camera ``camera`` (its rig's; 0:
        the first or only one; -1: road, sky, verge); the array is reused by the next
        call for a camera of the same image size."""
        self.open_renderer()
        assert self._renderer is not None
        self._sync_kinematics()
        m = self.mounts[camera]
        return self._renderer.segment(self.data, self._cam_ids[vehicle][camera], self._seg[(m.height, m.width)])

    def camera_truth(self, vehicle: str, camera: int = 0, *, min_visible_px: int = 1) -> CameraTruth:
        """Every entity ``vehicle``'s camera ``camera`` (its rig's; 0: the first or
        only one) shows now, from a segmentation render: its box (pixels of that
        camera's image), visible pixels and fraction, and distance along the ego's
        route (negative: behind its front)."""
        seg = self.segmentation(vehicle, camera)
        n = len(self.world.vehicles)
        counts = np.bincount(seg.ravel() + 1, minlength=n + 1)[1:]
        me = self._entity_index[vehicle]
        seen = [e for e in np.flatnonzero(counts >= min_visible_px).tolist() if e != me]
        ego = self._ego_truth(vehicle)
        if not seen:
            return CameraTruth(vehicle, self.sim_time_ns, (), ego)
        s_m, lat_m = self._path_coords(vehicle, seen)
        cam = self._cam_ids[vehicle][camera]
        intr = self.intrinsics(camera)
        w, h = self.mounts[camera].width, self.mounts[camera].height
        boxes = []
        for k, (e, box) in enumerate(zip(seen, pixel_boxes(seg, seen))):
            area, truncated = 0.0, False
            for g in self._entity_geoms[e]:
                a, t = silhouette_area(self.data.geom_xpos[g], self.data.geom_xmat[g].reshape(3, 3),
                                       self.model.geom_size[g], self.data.cam_xpos[cam],
                                       self.data.cam_xmat[cam].reshape(3, 3), intr.fx, intr.fy, intr.cx, intr.cy,
                                       w, h)
                area += a
                truncated = truncated or t
            vis = int(counts[e])
            spec = self.world.vehicles[e]
            boxes.append(VisibleBox(spec.name, e, spec.cls.label, box, vis,
                                    round(min(1.0, vis / area) if area > 0 else 1.0, 4), truncated,
                                    round(float(s_m[k]), 4), round(float(lat_m[k]), 4)))
        return CameraTruth(vehicle, self.sim_time_ns, tuple(boxes), ego)

    # -- ground truth --------------------------------------------------------

    def _states(self) -> _States:
        """(x, y, heading, vx, vy) of every entity at the present step (cached per step)."""
        if self._states_step == self.steps and self._states_cache is not None:
            return self._states_cache
        n = len(self.world.vehicles)
        st = self._static_states.copy() if n else np.zeros((5, 0))
        if self.egos:
            q, qv = self.data.qpos, self.data.qvel
            st[0, self._ego_ids] = self._x0 + q[self._qx]
            st[1, self._ego_ids] = self._y0 + q[self._qy]
            st[2, self._ego_ids] = q[self._qyaw]
            st[3, self._ego_ids] = qv[self._dx]
            st[4, self._ego_ids] = qv[self._dy]
        if len(self._scripted_ids):
            r = self._table.row(self.steps)
            st[0, self._scripted_ids] = self._table.pos[r, :, 0]
            st[1, self._scripted_ids] = self._table.pos[r, :, 1]
            st[2, self._scripted_ids] = 2 * np.arctan2(self._table.quat[r, :, 3], self._table.quat[r, :, 0])
            st[3, self._scripted_ids] = self._table.vel[r, :, 0]
            st[4, self._scripted_ids] = self._table.vel[r, :, 1]
        self._states_cache = (st[0], st[1], st[2], st[3], st[4])
        self._states_arr = st
        self._states_step = self.steps
        return self._states_cache

    def ground_truth(self, *, egos: tuple[str, ...] | None = None) -> GroundTruth:
        """Every entity's state (an ``EntityTable``: the same names tuple each time, so
        ``StateChanges`` compares columns), the truth of ``egos`` (default: every ego),
        and the collisions that began since the previous call."""
        self._sync_kinematics()
        t = self.sim_time_ns
        self._states()
        ents = EntityTable(self._names, self._classes, self._sizes, self._dims, self._ids, self._states_arr, t,
                           row_of=self._entity_index)
        truths = tuple(self._ego_truth(name) for name in (self.egos if egos is None else egos))
        collisions, self._new_collisions = tuple(self._new_collisions), []
        return GroundTruth(t, ents, truths, collisions)

    def truth_snapshot(self, *, egos: tuple[str, ...] | None = None) -> GroundTruth:
        """Every entity's state and the truth of ``egos`` (default: every ego) now,
        without taking the new collisions (they stay for the next ``ground_truth()``)."""
        pending = self._new_collisions
        gt = self.ground_truth(egos=egos)
        self._new_collisions = pending
        return GroundTruth(gt.sim_time_ns, gt.entities, gt.egos, ())

    def _path_coords(self, vehicle: str, entities: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """(distance along the ego's route from its front to each entity's nearest
        face, lateral offset of each from the ego's driving line) in metres."""
        s, lat, _, _, _ = self._route_geometry(vehicle, np.asarray(entities, int))
        return s, lat

    def _route_geometry(self, vehicle: str, idx: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per entity in ``idx``: gap along the route (front bumper to nearest face),
        lateral offset from the ego's line, half-extent across the route, speed
        along the route, and centre-to-centre distance along the route."""
        xs, ys, hs, vxs, vys = self._states()
        route = self._routes[vehicle]
        me = self._entity_index[vehicle]
        ps, pl = route.project(xs, ys)  # every entity's (the ego's among them: cheaper than picking first)
        os_, ol, es, el = ps[idx], pl[idx], ps[me], pl[me]
        _, _, rh = route.pose_at(os_)
        dh = hs[idx] - rh
        half_l, half_w = self._half_l[idx], self._half_w[idx]
        c, s = np.abs(np.cos(dh)), np.abs(np.sin(dh))
        along = half_l * c + half_w * s
        across = half_l * s + half_w * c
        gap = (os_ - es) - self._half_l[me] - along
        speed_along = vxs[idx] * np.cos(rh) + vys[idx] * np.sin(rh)
        return gap, ol - el, across, speed_along, os_ - es

    def _ego_truth(self, name: str) -> EgoTruth:
        speed = self.speed_mps(name)
        me = self._entity_index[name]
        others = self._others[me]
        best: tuple[float, int, float] | None = None
        if len(others):
            gap, lat, across, u, ds = self._route_geometry(name, others)
            ahead = np.flatnonzero((ds > 0) & (np.abs(lat) < self._half_w[me] + across))
            if len(ahead):
                k = int(ahead[np.argmin(gap[ahead])])
                best = (max(0.0, float(gap[k])), int(others[k]), float(u[k]))
        if best is None:
            return EgoTruth(name, None, None, speed, self.rules.decide(gap_m=None, speed_mps=speed))
        gap_m, e, obstacle_mps = best
        closing = speed - max(0.0, obstacle_mps)
        ttc = gap_m / closing if closing > 1e-3 else None
        return EgoTruth(name, gap_m, self.world.vehicles[e].name, speed,
                        self.rules.decide(gap_m=gap_m, speed_mps=speed, obstacle_speed_mps=obstacle_mps),
                        round(obstacle_mps, 4),
                        None if ttc is None else round(ttc, 4))

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
