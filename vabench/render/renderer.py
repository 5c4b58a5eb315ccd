"""Rendering one task family's scenes: clean model images and, apart from them, debug views.

A `SceneRenderer` owns one off-screen GL context and, per object model id (variant) of the
family, the MuJoCo model with one extra camera ("vabench_view") whose pose and FOV are set for
every image. The physics model is untouched: the camera is added to a render-only copy of the
scene spec, so qpos has the same layout as the simulator's.

Model images and debug images take separate paths on purpose. `render` has no options at all:
its visual settings are made fresh by `_model_option()` on every call, so nothing a person turns
on for debugging (contact points, frames, markers, labels) can reach an image a model sees.
`render_debug` builds its own settings from `DebugOverlays`.
"""

from __future__ import annotations

import io

import mujoco
import numpy as np
from PIL import Image, ImageDraw

from vabench.render import gl
from vabench.render.camera import FAR, NEAR, CameraPose
from vabench.render.debug import DebugOverlays
from vabench.sim_mjx import scene
from vabench.tasks.base import Task

VIEW_CAMERA = "vabench_view"
MAX_GEOMS = 4000


def render_spec(task: Task, variant: int, width: int, height: int) -> mujoco.MjSpec:
    """The task's scene with the view camera and an off-screen buffer of `width` x `height`."""
    spec = scene.build_spec(task.arms, lambda s: task.populate(s, variant))
    spec.worldbody.add_camera(name=VIEW_CAMERA, pos=[0.0, 0.0, 1.0])
    spec.visual.global_.offwidth = max(width, spec.visual.global_.offwidth)
    spec.visual.global_.offheight = max(height, spec.visual.global_.offheight)
    return spec


def _model_option() -> mujoco.MjvOption:
    """Visual settings of every model image: the default groups (visual geoms; no collision
    shapes, sites, frames, contacts or labels)."""
    return mujoco.MjvOption()


def _debug_option(overlays: DebugOverlays) -> mujoco.MjvOption:
    opt = mujoco.MjvOption()
    if overlays.contacts:
        opt.flags[mujoco.mjtVisFlag.mjVIS_CONTACTPOINT] = 1
        opt.flags[mujoco.mjtVisFlag.mjVIS_CONTACTFORCE] = 1
    if overlays.frames:
        opt.frame = mujoco.mjtFrame.mjFRAME_SITE
        opt.sitegroup[:] = 1
    if overlays.collision_geoms:
        opt.geomgroup[3] = 1
    return opt


class _VariantScene:
    """One object model id: model, data, abstract scene and GPU resources."""

    def __init__(self, spec: mujoco.MjSpec):
        self.model = spec.compile()
        m = self.model
        m.vis.map.znear = NEAR / m.stat.extent  # MuJoCo scales the clip planes by the extent
        m.vis.map.zfar = FAR / m.stat.extent
        # Decor sizes (frames, contact points, force arrows) scale with meansize; the scene's
        # automatic value (about the table's size) makes debug overlays hide the gripper. Only
        # debug views draw decor, so model images are unaffected.
        m.stat.meansize = 0.02
        self.data = mujoco.MjData(m)
        self.cam_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, VIEW_CAMERA)
        self.scene = mujoco.MjvScene(m, maxgeom=MAX_GEOMS)
        self.context = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_150)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self.camera.fixedcamid = self.cam_id
        self.pads = [
            (
                mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{arm}_pad_a"),
                mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{arm}_pad_b"),
            )
            for arm in ("left", "right")
        ]

    def pose(self, qpos: np.ndarray, camera: CameraPose, physics: bool) -> None:
        m, d = self.model, self.data
        if qpos.shape != (m.nq,):
            raise ValueError(f"qpos has shape {qpos.shape}; this scene needs ({m.nq},)")
        d.qpos[:] = qpos
        m.cam_pos[self.cam_id] = camera.pos
        m.cam_quat[self.cam_id] = camera.quat()
        m.cam_fovy[self.cam_id] = camera.fovy
        if physics:  # contacts for the debug overlay
            mujoco.mj_forward(m, d)
        else:  # positions are all an image needs
            mujoco.mj_kinematics(m, d)
            mujoco.mj_camlight(m, d)


class SceneRenderer:
    """Renders scenes of one task family from arbitrary camera poses (one GL context)."""

    def __init__(
        self, task: Task, platform: str, max_width: int = 1280, max_height: int = 960
    ) -> None:
        self.task = task
        self.platform = platform
        self.max_size = (max_width, max_height)
        self._gl = gl.make_context(platform, max_width, max_height)
        self.gl_info = gl.describe(platform)
        self._variants: dict[int, _VariantScene] = {}

    def _scene(self, variant: int) -> _VariantScene:
        if variant not in self._variants:
            if not 0 <= variant < len(self.task.variants):
                raise ValueError(
                    f"variant {variant} out of range for {self.task.name} "
                    f"({len(self.task.variants)} object model ids)"
                )
            spec = render_spec(self.task, variant, *self.max_size)
            self._gl.make_current()
            self._variants[variant] = _VariantScene(spec)
        return self._variants[variant]

    def _check_size(self, width: int, height: int) -> None:
        if not (0 < width <= self.max_size[0] and 0 < height <= self.max_size[1]):
            raise ValueError(
                f"image size {width}x{height} exceeds this renderer's {self.max_size[0]}x"
                f"{self.max_size[1]} buffer (or is not positive)"
            )

    def _update_scene(self, vs: _VariantScene, opt: mujoco.MjvOption) -> None:
        self._gl.make_current()
        mujoco.mjv_updateScene(
            vs.model, vs.data, opt, None, vs.camera, mujoco.mjtCatBit.mjCAT_ALL, vs.scene
        )

    def _finish(self, vs: _VariantScene, width: int, height: int) -> np.ndarray:
        rect = mujoco.MjrRect(0, 0, width, height)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, vs.context)
        mujoco.mjr_render(rect, vs.scene, vs.context)
        rgb = np.empty((height, width, 3), np.uint8)
        mujoco.mjr_readPixels(rgb, None, rect, vs.context)
        return np.ascontiguousarray(rgb[::-1])  # OpenGL rows run bottom-up

    def render(
        self, qpos: np.ndarray, variant: int, camera: CameraPose, width: int, height: int
    ) -> np.ndarray:
        """The clean RGB image (height, width, 3) a model sees of this state."""
        self._check_size(width, height)
        vs = self._scene(variant)
        vs.pose(np.asarray(qpos, float), camera, physics=False)
        self._update_scene(vs, _model_option())
        return self._finish(vs, width, height)

    def render_debug(
        self,
        qpos: np.ndarray,
        variant: int,
        camera: CameraPose,
        width: int,
        height: int,
        overlays: DebugOverlays,
    ) -> np.ndarray:
        """An image for people: the same view with the requested overlays."""
        self._check_size(width, height)
        vs = self._scene(variant)
        vs.pose(np.asarray(qpos, float), camera, physics=overlays.contacts)
        self._update_scene(vs, _debug_option(overlays))
        if overlays.gc_markers:
            self._add_gc_markers(vs)
        rgb = self._finish(vs, width, height)
        if overlays.label:
            img = Image.fromarray(rgb)
            draw = ImageDraw.Draw(img)
            draw.rectangle((0, 0, 12 + 7 * len(overlays.label), 22), fill=(0, 0, 0))
            draw.text((6, 5), overlays.label, fill=(255, 255, 255))
            rgb = np.asarray(img)
        return rgb

    def _add_gc_markers(self, vs: _VariantScene) -> None:
        for a, b in vs.pads:
            if a < 0 or b < 0 or vs.scene.ngeom >= vs.scene.maxgeom:
                continue
            gc = (vs.data.site_xpos[a] + vs.data.site_xpos[b]) / 2
            geom = vs.scene.geoms[vs.scene.ngeom]
            mujoco.mjv_initGeom(
                geom,
                mujoco.mjtGeom.mjGEOM_SPHERE,
                np.array([0.008, 0, 0]),
                gc,
                np.eye(3).ravel(),
                np.array([1.0, 0.1, 0.8, 0.9], np.float32),
            )
            vs.scene.ngeom += 1

    def close(self) -> None:
        for vs in self._variants.values():
            vs.context.free()
        self._variants.clear()
        self._gl.free()


def encode_png(rgb: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()
