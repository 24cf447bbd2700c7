"""Offscreen rendering of every ego camera with one OpenGL context.

One ``SceneRenderer`` serves all cameras (FACTS: one context is faster than one per
camera). ``rgb`` draws a camera image; ``segment`` draws the same view in
MuJoCo's segmentation mode with the road and ground left out (geom group
``ROAD_GROUP`` off: flat, they occlude nothing), which rasterises only the entities
and so costs a fraction of a colour image. The segment ids are decoded straight to
entity indices through a lookup table, without the per-pixel (object id, type)
pairs ``mujoco.Renderer`` builds.

Call ``hil.scenarios.gl.select_backend()`` before importing this module.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hil.common.errors import SimulationError
from hil.scenarios.road import ROAD_GROUP

BACKGROUND = -1


class SceneRenderer:
    """Colour and segmentation images of a model's cameras. A context manager;
    ``close()`` is idempotent.

    Raises:
        SimulationError: the OpenGL context cannot be created.
    """

    def __init__(self, model: mujoco.MjModel, *, width: int, height: int, shadows: bool = False,
                 reflections: bool = False, geom_entity: np.ndarray | None = None) -> None:
        """``geom_entity``: entity index of every model geom (-1: none), for ``segment``."""
        self._gl: mujoco.GLContext | None = None
        self._ctx: mujoco.MjrContext | None = None
        self.model, self.width, self.height = model, width, height
        try:
            self._gl = mujoco.GLContext(max(width, 1), max(height, 1))
            self._gl.make_current()
            self._ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._ctx)
        except Exception as err:  # mujoco raises bare RuntimeError/ImportError here
            self.close()
            raise SimulationError(f"cannot start the MuJoCo renderer: {err}") from err
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._scene = mujoco.MjvScene(model, maxgeom=model.ngeom + 64)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadows
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = reflections
        self._opt = mujoco.MjvOption()
        self._seg_scene = mujoco.MjvScene(model, maxgeom=model.ngeom + 64)
        self._seg_scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
        self._seg_scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        self._seg_opt = mujoco.MjvOption()
        self._seg_opt.geomgroup[ROAD_GROUP] = 0
        self._cams: dict[int, mujoco.MjvCamera] = {}
        self._raw = np.empty((height, width, 3), np.uint8)
        self._raws: dict[tuple[int, int], np.ndarray] = {}  # smaller cameras' read-back buffers
        self._geom_entity = (np.full(model.ngeom, BACKGROUND, np.int32) if geom_entity is None
                             else np.asarray(geom_entity, np.int32))
        self._lut = np.full(256 * 256, BACKGROUND, np.int32)

    def _camera(self, cam_id: int) -> mujoco.MjvCamera:
        cam = self._cams.get(cam_id)
        if cam is None:
            if not 0 <= cam_id < self.model.ncam:
                raise SimulationError(f"camera id {cam_id} outside 0..{self.model.ncam - 1}")
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = cam_id
            self._cams[cam_id] = cam
        return cam

    def rgb(self, data: mujoco.MjData, cam_id: int, out: np.ndarray) -> np.ndarray:
        """Draw camera ``cam_id`` into ``out`` (height x width x 3 uint8, top row first)."""
        if self._ctx is None or self._gl is None:
            raise SimulationError("renderer is closed")
        self._gl.make_current()
        mujoco.mjv_updateScene(self.model, data, self._opt, None, self._camera(cam_id),
                               mujoco.mjtCatBit.mjCAT_ALL.value, self._scene)
        rect, raw = self._view(out)
        mujoco.mjr_render(rect, self._scene, self._ctx)
        mujoco.mjr_readPixels(raw, None, rect, self._ctx)
        np.copyto(out, raw[::-1])  # OpenGL's first row is the bottom one
        return out

    def _view(self, out: np.ndarray) -> tuple[mujoco.MjrRect, np.ndarray]:
        """The viewport and read-back buffer of an image of ``out``'s size: a smaller
        camera of a rig draws into the bottom-left of the buffer."""
        h, w = out.shape[:2]
        if (h, w) == (self.height, self.width):
            return self._rect, self._raw
        return mujoco.MjrRect(0, 0, w, h), self._raws.setdefault((h, w), np.empty((h, w, 3), np.uint8))

    def segment(self, data: mujoco.MjData, cam_id: int, out: np.ndarray) -> np.ndarray:
        """Entity index of every pixel of camera ``cam_id`` into ``out`` (height x width
        int32, top row first; ``BACKGROUND`` where no entity is seen)."""
        if self._ctx is None or self._gl is None:
            raise SimulationError("renderer is closed")
        self._gl.make_current()
        scn = self._seg_scene
        mujoco.mjv_updateScene(self.model, data, self._seg_opt, None, self._camera(cam_id),
                               mujoco.mjtCatBit.mjCAT_ALL.value, scn)
        rect, raw = self._view(out)
        mujoco.mjr_render(rect, scn, self._ctx)
        mujoco.mjr_readPixels(raw, None, rect, self._ctx)
        # Segment id + 1 is encoded in the colour (red = low byte, green = high byte);
        # 0 is background. Map each to the entity of its geom.
        lut = self._lut
        n = scn.ngeom
        lut[: n + 2] = BACKGROUND
        for i in range(n):
            g = scn.geoms[i]
            if g.segid >= 0 and g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lut[g.segid + 1] = self._geom_entity[g.objid]
        raw = raw[::-1]
        if n + 1 < 256:
            np.take(lut, raw[:, :, 0], out=out)
        else:
            ids = raw[:, :, 0].astype(np.int32) | (raw[:, :, 1].astype(np.int32) << 8)
            np.take(lut, ids, out=out)
        return out

    def close(self) -> None:
        ctx, gl = getattr(self, "_ctx", None), getattr(self, "_gl", None)
        self._ctx = self._gl = None
        if ctx is not None:
            if gl is not None:
                gl.make_current()
            ctx.free()
        if gl is not None:
            gl.free()

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the GL library may be gone
            pass
