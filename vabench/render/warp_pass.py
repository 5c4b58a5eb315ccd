"""One render batch of the Warp renderer: `n_worlds` worlds of one task family at one image
size, each ray traced through its own camera (`vabench.render.warp_renderer` makes, sizes and
reuses them).

A pass owns a render context (BVHs, textures, buffers) and a model whose per-world fields hold
each world's object variant and FOV. `draw` writes the states of its items (gathered on the
device from a Warp physics batch, or uploaded from host copies), runs the kinematics, places
each world's camera, refits the BVH and ray traces every world in one launch; `packed` brings
the pixels to the host, `rgb_on_device` unpacks them for the device JPEG encoder.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src.bvh import compute_bvh_group_roots  # mujoco-warp 4.0.0 (pinned)

from vabench.render import warp_jpeg
from vabench.render.camera import FAR, NEAR
from vabench.render.images import RenderItem
from vabench.render.renderer import VIEW_CAMERA, render_spec
from vabench.sim_mjx.warp import streams
from vabench.sim_mjx.warp.model import RENDER_IGNORED, VariantFields, WarpModel
from vabench.tasks.base import Task


@wp.kernel
def _place_cameras(
    cam: int,
    pos: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.mat33),
    fovy: wp.array(dtype=float),
    cam_xpos: wp.array2d(dtype=wp.vec3),
    cam_xmat: wp.array2d(dtype=wp.mat33),
    cam_fovy: wp.array2d(dtype=float),
):
    """World w looks through its own camera (kinematics placed the model's, overwritten here)."""
    w = wp.tid()
    cam_xpos[w, cam] = pos[w]
    cam_xmat[w, cam] = rot[w]
    cam_fovy[w, cam] = fovy[w]


@wp.kernel
def _unpack_rgb(packed: wp.array2d(dtype=wp.uint32), width: int, rgb: wp.array4d(dtype=wp.uint8)):
    """0x??RRGGBB per pixel -> (H, W, 3) bytes, for the device JPEG encoder."""
    w, p = wp.tid()
    v = packed[w, p]
    y, x = p // width, p % width
    rgb[w, y, x, 0] = wp.uint8((v >> wp.uint32(16)) & wp.uint32(255))
    rgb[w, y, x, 1] = wp.uint8((v >> wp.uint32(8)) & wp.uint32(255))
    rgb[w, y, x, 2] = wp.uint8(v & wp.uint32(255))


IDLE_CAMERA_HEIGHT = 100.0
"""Metres above the world's origin (the floor) where a pass's idle worlds (beyond its
request's items) look straight up: every world of a pass is ray traced, and an idle camera left
at the origin looking down hit the floor in every pixel and cast a shadow ray through the
scene, as costly as an image. Looking up, a ray leaves the scene's bounds at once and reads
the sky. The render megakernel is most of the engine processes' GPU kernel time
(docs/PERFORMANCE.md, "Whole suite on one GPU") and a pass is up to a third larger than its
request (`pass_size`)."""
IDLE_CAMERA_ROT = np.diag([1.0, -1.0, -1.0]).astype(np.float32)
"""A camera looks along its -z axis: this frame's -z is the world's +z (up)."""

RENDER_BLOCK_DIM = 256
"""Threads a block of the render megakernel (MuJoCo Warp's default: 64). Same pixels, a pass
of the basket ~13 % shorter; 128 and 256 are alike (`benchmarks/render_options.py`;
docs/PERFORMANCE.md, "Renderer")."""


def render_context(
    model: mujoco.MjModel, n_worlds: int, width: int, height: int, **options: Any
) -> Any:
    """MuJoCo Warp's render context of a pass: RGB only, one camera a world with its own FOV,
    textures, ray-cast shadows and the skybox (`options` override them:
    `benchmarks/render_options.py` measures what each costs)."""
    settings: dict[str, Any] = {
        "nworld": n_worlds,
        "cam_res": (width, height),
        "render_rgb": True,
        "render_depth": False,
        "render_seg": False,
        "use_textures": True,
        "use_shadows": True,
        "cam_active": [VIEW_CAMERA],
        "use_precomputed_rays": False,  # per-world FOV
        "render_skybox": True,
    }
    return mjw.create_render_context(model, **(settings | options))


def rebuild_scene_bvh(rc: Any, n_worlds: int) -> None:
    """Build `rc`'s scene BVH again from its bounds as last refit (MuJoCo Warp builds it once,
    at qpos0: see `RenderPass._rebuild_bvh`), and each world's root in it."""
    rc.bvh = wp.Bvh(rc.lower, rc.upper, groups=rc.group, constructor="sah")
    rc.bvh_id = rc.bvh.id
    wp.launch(compute_bvh_group_roots, dim=n_worlds, inputs=[rc.bvh.id], outputs=[rc.group_root])


def render_models(task: Task, width: int, height: int) -> list[mujoco.MjModel]:
    """The render model of every object variant of `task` (the GL path's, same clip planes)."""
    models = []
    for variant in range(len(task.variants)):
        m = render_spec(task, variant, width, height).compile()
        m.vis.map.znear = NEAR / m.stat.extent  # MuJoCo scales the clip planes by the extent
        m.vis.map.zfar = FAR / m.stat.extent
        models.append(m)
    return models


def pass_size(n: int) -> int:
    """Worlds of the pass that renders n images: the next of 1, 2, 3, 4, 6, 8, 12, 16, 24, ...
    Every world of a pass is ray traced, so a pass larger than the request wastes work (at most
    a third here); a pass of every exact size would build a render context for every request
    size the engine happens to send."""
    power = 1 << max(0, (n - 1).bit_length() - 1)  # the largest power of two below n (or 1)
    for size in (power, 3 * power // 2, 2 * power):
        if size >= n:
            return max(size, 1)
    raise AssertionError(n)


def pass_bytes(
    width: int, height: int, n_worlds: int, device_jpeg: bool | str, subsampling: str = "444"
) -> int:
    """Device memory a pass needs beyond its model: packed pixels (+ RGB bytes for nvJPEG and
    nvImageCodec, `device_jpeg` true, or the buffers of `warp_jpeg` at `subsampling`,
    "kernels") and a margin for BVH nodes and data per world."""
    jpeg = 0
    if device_jpeg == "kernels":
        jpeg = warp_jpeg.bytes_per_world(width, height, subsampling)
    elif device_jpeg:
        jpeg = 3 * width * height
    per_world = width * height * 4 + jpeg + 256 * 1024
    return per_world * n_worlds


class RenderPass:
    """A render batch of `n_worlds` worlds of one task family at one image size. Its JPEG
    (`device_jpeg`): on the host (False), from RGB frames it unpacks on the device (True: nvJPEG
    or nvImageCodec), or by its own `warp_jpeg.WarpJpeg` ("kernels"; `jpeg_seconds` sums where
    that encoder's time goes). `variants`: `variant_fields(models, RENDER_IGNORED)`, which the
    renderer finds once a family (most of a pass's build otherwise)."""

    def __init__(
        self,
        models: Sequence[mujoco.MjModel],
        n_worlds: int,
        width: int,
        height: int,
        device_jpeg: bool | str,
        high_priority: bool = False,
        jpeg_seconds: dict[str, float] | None = None,
        variants: VariantFields | None = None,
    ):
        self.n_worlds, self.width, self.height = n_worlds, width, height
        m0 = models[0]
        self.cam = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_CAMERA, VIEW_CAMERA)
        self.wm = WarpModel(
            models, n_worlds, RENDER_IGNORED, per_world=("cam_fovy",), variants=variants
        )
        self.m = self.wm.model
        # Kinematics only: no contacts or constraints are ever computed in these worlds.
        self.d = mjw.make_data(m0, nworld=n_worlds, nconmax=1, njmax=1)
        self.rc = render_context(m0, n_worlds, width, height)
        self.m.block_dim.render = RENDER_BLOCK_DIM
        self._bvh_posed = False
        self.slots = wp.zeros(n_worlds, dtype=int)
        self.pos = wp.zeros(n_worlds, dtype=wp.vec3)
        self.rot = wp.zeros(n_worlds, dtype=wp.mat33)
        self.fovy = wp.zeros(n_worlds, dtype=float)
        self.rgb = None
        self.jpeg: warp_jpeg.WarpJpeg | None = None
        if device_jpeg == "kernels":  # above the ray tracing in priority, as the other encoders
            priority = "greatest" if high_priority else "middle"
            self.jpeg = warp_jpeg.WarpJpeg(
                n_worlds, width, height, self.d.qpos.device, priority, jpeg_seconds
            )
        elif device_jpeg:
            self.rgb = wp.zeros((n_worlds, height, width, 3), dtype=wp.uint8)
        self._variants = np.zeros(n_worlds, np.int32)
        # Its own stream (the renderer queues a pass there and waits for it with the device's
        # lock released: sim_mjx.warp.streams), and who is using it: one request at a time,
        # from queueing to the last JPEG; a pass in use is never evicted.
        self.stream = streams.new_stream(
            self.d.qpos.device, "greatest" if high_priority else "least"
        )
        if self.stream is not None:  # the arrays above were made on the device's current stream
            self.stream.wait_stream(wp.get_stream(self.d.qpos.device))
        self.lock = threading.Lock()
        self.evicted = False
        self._host: wp.array | None = None

    def draw(self, items: Sequence[RenderItem], source: Any | None) -> None:
        """Ray trace `items` into worlds 0..len(items)-1 (queued on the device; the caller
        holds the device lock). `source`: a physics batch to gather the states from."""
        n, nq = len(items), self.d.qpos.shape[1]
        # Every upload first, while the pass's stream is idle: a copy from pageable host memory
        # waits for the stream's queued work, and after the gather that is the source batch's
        # action in flight, waited for with the device lock held (seen in a GPU profile).
        variants = self._variants.copy()
        variants[:n] = [it.variant for it in items]
        self.wm.assign(variants)
        pos = np.zeros((self.n_worlds, 3), np.float32)
        pos[n:, 2] = IDLE_CAMERA_HEIGHT
        rot = np.tile(IDLE_CAMERA_ROT, (self.n_worlds, 1, 1))
        fovy = np.full(self.n_worlds, 45.0, np.float32)
        for i, it in enumerate(items):
            pos[i], rot[i], fovy[i] = it.camera.pos, it.camera.rot, it.camera.fovy
        self.pos.assign(pos)
        self.rot.assign(rot)
        self.fovy.assign(fovy)
        if source is not None:
            self.slots.assign(np.array([it.slot for it in items] + [0] * (self.n_worlds - n)))
            source.copy_qpos(self.slots, self.d.qpos)
        else:
            qpos = np.zeros((self.n_worlds, nq), np.float32)
            qpos[:n] = np.stack([np.asarray(it.qpos, np.float32) for it in items])
            qpos[n:] = qpos[0]  # idle worlds at a real pose, as gathered ones (slot 0)
            self.d.qpos.assign(qpos)
        mjw.kinematics(self.m, self.d)
        mjw.camlight(self.m, self.d)
        wp.launch(
            _place_cameras,
            dim=self.n_worlds,
            inputs=[self.cam, self.pos, self.rot, self.fovy],
            outputs=[self.d.cam_xpos, self.d.cam_xmat, self.m.cam_fovy],
        )
        mjw.refit_bvh(self.m, self.d, self.rc)
        if not self._bvh_posed:
            self._rebuild_bvh()
        mjw.render(self.m, self.d, self.rc)

    def _rebuild_bvh(self) -> None:
        """Build the scene's BVH again, once, around the first items' poses (bounds just
        refit). MuJoCo Warp builds it at qpos0, where every free object sits at the world's
        origin, and afterwards only refits it: the tree keeps grouping the objects as if they
        were together, and rays visit more nodes. Built around a scene as the episodes set it,
        the tree stays good while things move: the basket's pass ~17 % shorter, the same pixels
        but 1 in 30 million (`benchmarks/render_options.py`; docs/PERFORMANCE.md, "Renderer").
        Once a pass: the build copies the bounds to the host,
        which waits for the pass's queued work with the device's lock held (with
        `state_on_device`, that includes the source batch's queued action)."""
        rebuild_scene_bvh(self.rc, self.n_worlds)
        self._bvh_posed = True

    def queue_packed(self) -> None:
        """Queue the copy of every world's packed pixels to pinned host memory (GPU; the
        caller holds the device lock with this pass's stream current). `packed` reads them once
        the pass's event has passed."""
        if self.rc.rgb_data.device.is_cuda:
            if self._host is None:
                self._host = wp.empty_like(self.rc.rgb_data, device="cpu", pinned=True)
            wp.copy(self._host, self.rc.rgb_data)

    def packed(self, n: int) -> np.ndarray:
        """(n, H, W) uint32 pixels of the first n worlds, a host copy of their own (the next
        pass reuses the buffer while these are still being encoded)."""
        rows = self._host if self._host is not None else self.rc.rgb_data
        return rows.numpy()[:n].copy().reshape(n, self.height, self.width)

    def rgb_on_device(self) -> wp.array:
        assert self.rgb is not None
        wp.launch(
            _unpack_rgb,
            dim=(self.n_worlds, self.width * self.height),
            inputs=[self.rc.rgb_data, self.width],
            outputs=[self.rgb],
        )
        return self.rgb
