"""The Warp renderer on Warp's CPU device: the same kernels a GPU runs, one world per image.

What is checked: the backend choice and its messages; images that match the GL renderer's
(same framing, same look within a few grey levels); every image independent of the batch it is
rendered in, of its position and of its neighbours' variants and cameras; passes split by size
without changing a pixel; the state read on the device from a Warp physics batch equal to its
host copy, for each of two batches of one task; passes kept within their memory budget; JPEG
with the same settings as the GL path. Throughput is measured on a GPU by
benchmarks/render_throughput.py (docs/PERFORMANCE.md, "Renderer"), never here.
"""

from __future__ import annotations

import base64
import io
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("warp", reason="the Warp renderer needs warp-lang (the [test] extra has it)")
pytest.importorskip("mujoco_warp", reason="the Warp renderer needs mujoco-warp ([test] extra)")

from vabench.render import availability, backends
from vabench.render import camera as cam
from vabench.render.__main__ import reset_state
from vabench.render.images import ImageSettings, RenderError, RenderItem, encode_jpeg
from vabench.render.warp_renderer import WarpRenderPool
from vabench.render.worker import RenderPool
from vabench.sim_mjx.backends import BackendUnavailable
from vabench.tasks.manifests import verified_seeds

CUBE = "place_single_cube"
SHOE = "place_shoe"  # ten object variants: per-world model fields
SIZE = ImageSettings(160, 120, 95)
EXACT = ImageSettings(160, 120, 100, "444")  # for pixel comparisons with GL
# GL (rasterised, MSAA, shadow map) and Warp (ray traced, one sample per pixel, ray-cast
# shadows) draw the same scene: measured 1.7-4.4 grey levels apart on average per image; an
# object moved by one pixel would move far more.
MEAN_GAP = 6.0
CENTROID_PX = 1.5


def _decode(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"))


def _items(task: str, seed: int) -> list[RenderItem]:
    arms = ("left", "right") if task == SHOE else ("right",)
    qpos, variant, gcs = reset_state(task, seed, "c")
    poses = [cam.head_view(gcs, arms), *cam.passive_bundle(gcs, arms)]
    return [RenderItem(qpos, variant, p) for p in poses]


@pytest.fixture(scope="module")
def warp_pool():
    os.environ["VABENCH_WARP_DEVICE"] = "cpu"
    try:
        # states read on the device where a request names its physics batch (the tests of
        # that path); off by default: `test_by_default_states_come_from_the_host_copies`
        with WarpRenderPool(max_size=(320, 240), state_on_device=True) as pool:
            yield pool
    finally:
        os.environ.pop("VABENCH_WARP_DEVICE", None)


@pytest.fixture(scope="module")
def gl_pool():
    with RenderPool(workers=1, max_size=(320, 240), timeout_s=60) as pool:
        yield pool


@pytest.fixture(scope="module")
def cube_items():
    return _items(CUBE, verified_seeds(CUBE)[0])


@pytest.fixture(scope="module")
def shoe_items():
    seeds = verified_seeds(SHOE)
    items = _items(SHOE, seeds[0])[:2]
    for seed in seeds[1:]:  # a second variant, so that neighbouring worlds differ in objects
        more = _items(SHOE, seed)[:2]
        if more[0].variant != items[0].variant:
            return items + more
    raise AssertionError("place_shoe's verified seeds all use one variant")


def _red_centroid(rgb: np.ndarray) -> np.ndarray:
    r, g, b = (rgb[..., k].astype(int) for k in range(3))
    ys, xs = np.nonzero((r > 110) & (g < 60) & (b < 60))
    assert len(xs) > 10, "the red cube is not in the image"
    return np.array([xs.mean(), ys.mean()])


# -- choosing the renderer ---------------------------------------------------------------
def test_choice_and_its_reasons(monkeypatch):
    monkeypatch.setattr(availability, "warp_problem", lambda device: None)
    assert backends.resolve_renderer("auto", "cuda:0").backend == "warp"
    assert backends.resolve_renderer("gl").backend == "gl"
    monkeypatch.setattr(
        availability, "warp_problem", lambda device: "the Warp backend needs the package warp-lang"
    )
    auto = backends.resolve_renderer("auto", "cuda:0")
    assert auto.backend == "gl" and "warp-lang" in auto.reason
    with pytest.raises(BackendUnavailable, match="the Warp renderer needs the package warp-lang"):
        backends.resolve_renderer("warp", "cuda:0")
    with pytest.raises(ValueError, match="render backend must be one of"):
        backends.resolve_renderer("vulkan")


def test_no_gpu_gets_one_clear_message(monkeypatch, tmp_path):
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("this machine has a CUDA GPU")
    monkeypatch.delenv("VABENCH_WARP_DEVICE", raising=False)
    with pytest.raises(BackendUnavailable, match=r"needs an NVIDIA GPU.*render backend gl"):
        WarpRenderPool().start()
    env = {k: v for k, v in os.environ.items() if k != "VABENCH_WARP_DEVICE"}
    proc = subprocess.run(
        [sys.executable, "-m", "vabench.render", "snapshot", "--task", CUBE, "--seed", "1000"]
        + ["--renderer", "warp", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode != 0
    assert "the Warp renderer needs an NVIDIA GPU" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_sweep_config_takes_the_render_backend(tmp_path):
    from vabench.config import SweepConfigError, load_config

    def write(render: str):
        path = tmp_path / "s.yaml"
        path.write_text(
            "models: [{name: m, api: openai_chat, base_url: embedded}]\n"
            f"tracks: [active]\ntasks: [{CUBE}]\nseeds: [1000]\nruns: 1\nrender: {render}\n"
        )
        return path

    config = load_config(write("{backend: warp, subsampling: '444', quality: 90}"))
    assert config.render.backend == "warp"
    assert config.render.image_settings() == ImageSettings(1280, 960, 90, "444")
    assert load_config(write("{}")).render.backend == "auto"
    with pytest.raises(SweepConfigError, match=r"render\.backend"):
        load_config(write("{backend: vulkan}"))
    with pytest.raises(SweepConfigError, match=r"render\.subsampling"):
        load_config(write("{subsampling: '411'}"))


# -- the images --------------------------------------------------------------------------
def test_images_match_gl(warp_pool, gl_pool, cube_items):
    warp = warp_pool.render_rgb(CUBE, cube_items, EXACT)
    gl = [_decode(j) for j in gl_pool.render(CUBE, cube_items, EXACT)]
    assert warp.shape == (6, 120, 160, 3) and warp.dtype == np.uint8
    for view, w, g in zip(cube_items, warp, gl, strict=True):
        gap = float(np.abs(w.astype(int) - g).mean())
        assert gap <= MEAN_GAP, (view.camera.label, gap)
        shift = np.linalg.norm(_red_centroid(w) - _red_centroid(g))
        assert shift <= CENTROID_PX, (view.camera.label, shift)  # same framing
    assert len({w.tobytes() for w in warp}) == 6  # every view differs


def test_variants_per_world_match_gl(warp_pool, gl_pool, shoe_items):
    warp = warp_pool.render_rgb(SHOE, shoe_items, EXACT)
    gl = [_decode(j) for j in gl_pool.render(SHOE, shoe_items, EXACT)]
    for item, w, g in zip(shoe_items, warp, gl, strict=True):
        assert float(np.abs(w.astype(int) - g).mean()) <= MEAN_GAP, item.variant


def test_an_image_does_not_depend_on_its_batch(warp_pool, cube_items, shoe_items):
    together = warp_pool.render_rgb(SHOE, shoe_items, SIZE)
    backwards = warp_pool.render_rgb(SHOE, shoe_items[::-1], SIZE)[::-1]
    alone = np.concatenate([warp_pool.render_rgb(SHOE, [it], SIZE) for it in shoe_items])
    assert np.array_equal(together, backwards)
    assert np.array_equal(together, alone)
    cube = warp_pool.render_rgb(CUBE, cube_items, SIZE)
    padded = warp_pool.render_rgb(CUBE, cube_items + cube_items[:3], SIZE)  # another pass size
    assert np.array_equal(cube, padded[:6]) and np.array_equal(cube[:3], padded[6:])


def test_a_request_larger_than_a_pass_is_split_without_changing_a_pixel(cube_items, warp_pool):
    os.environ["VABENCH_WARP_DEVICE"] = "cpu"
    try:
        with WarpRenderPool(max_size=(320, 240), max_pass=4) as small:
            split = small.render_rgb(CUBE, cube_items, SIZE)
            assert small.stats.passes == 2  # 6 images, at most 4 per pass
    finally:
        os.environ.pop("VABENCH_WARP_DEVICE", None)
    assert np.array_equal(split, warp_pool.render_rgb(CUBE, cube_items, SIZE))


def test_jpeg_is_encoded_like_the_gl_path(warp_pool, gl_pool, cube_items):
    from vabench.render.images import encode_jpeg

    for settings in (SIZE, ImageSettings(160, 120, 80, "444")):
        jpegs = warp_pool.render(CUBE, cube_items[:2], settings)
        rgb = warp_pool.render_rgb(CUBE, cube_items[:2], settings)
        # The packed pixels go to libjpeg-turbo as BGRX: the same bytes as encoding the RGB.
        expected = [encode_jpeg(f, settings.quality, settings.subsampling) for f in rgb]
        assert jpegs == expected
        for jpeg in [*jpegs, *gl_pool.render(CUBE, cube_items[:1], settings)]:
            img = Image.open(io.BytesIO(jpeg))
            assert img.size == (160, 120) and img.format == "JPEG"
            sampling = img.layer[0][1:3]  # luma's sampling factors: (2, 2) for 4:2:0
            assert sampling == ((1, 1) if settings.subsampling == "444" else (2, 2))


def test_bad_requests_fail_at_once(warp_pool, cube_items):
    item = cube_items[0]
    with pytest.raises(RenderError, match="variant 3 out of range"):
        warp_pool.render(CUBE, [RenderItem(item.qpos, 3, item.camera)], SIZE)
    with pytest.raises(RenderError, match="qpos has shape"):
        warp_pool.render(CUBE, [RenderItem(item.qpos[:-1], 0, item.camera)], SIZE)
    with pytest.raises(RenderError, match="exceeds the renderer's maximum"):
        warp_pool.render(CUBE, [item], ImageSettings(640, 480))
    with pytest.raises(RenderError, match="unknown task"):
        warp_pool.render("no_such_task", [item], SIZE)
    with pytest.raises(RenderError, match="drawn by the GL renderer"):
        warp_pool.render_debug(CUBE, [item], None)
    assert len(warp_pool.render(CUBE, [item], SIZE)) == 1  # still usable


def test_the_jpeg_choice_is_checked(monkeypatch):
    with pytest.raises(ValueError, match="jpeg must be one of"):
        WarpRenderPool(device="cpu", jpeg="gpu")
    monkeypatch.setenv("VABENCH_WARP_JPEG", "nvjpeg")
    pool = WarpRenderPool(device="cpu")
    assert pool.jpeg == "nvjpeg"  # the environment's default (measuring side by side)
    with pytest.raises(RenderError, match="needs a GPU and nvJPEG"):
        pool.start()


class _DeviceJpegStandIn:
    """Stands in for nvImageCodec on Warp's CPU device (no GPU here): encodes the frames it is
    handed, and records whether the pass they came from was still held while it did."""

    def __init__(self, pool):
        self.pool = pool
        self.seconds = {"encoding": 0.0}
        self.pass_held: list[bool] = []

    def encode(self, frames, settings, stream):
        self.pass_held.append(any(p.lock.locked() for p, _ in self.pool._passes.values()))
        return [encode_jpeg(f, settings.quality, settings.subsampling) for f in frames.numpy()]


@pytest.mark.parametrize("concurrent", [1, 2])
def test_device_jpeg_path_with_requests_side_by_side(concurrent, cube_items, monkeypatch):
    """The device-JPEG branch of a pass (nvImageCodec's on a GPU), on Warp's CPU device with a
    stand-in encoder: the same bytes whether requests run one at a time or side by side, and
    with more than one the pass is free again while its frames (a copy) are encoded."""
    monkeypatch.setenv("VABENCH_WARP_DEVICE", "cpu")
    with WarpRenderPool(max_size=(320, 240), concurrent_requests=concurrent) as pool:
        encoder = _DeviceJpegStandIn(pool)
        pool._device_jpeg = encoder
        monkeypatch.setattr(pool, "_jpeg_encoder", lambda urgent: (encoder, 0))
        alone = pool.render(CUBE, cube_items, SIZE)
        with ThreadPoolExecutor(3) as threads:
            side_by_side = list(
                threads.map(lambda _: pool.render(CUBE, cube_items, SIZE), range(3))
            )
    assert all(images == alone for images in side_by_side)
    assert all(jpeg[:2] == b"\xff\xd8" for jpeg in alone)
    assert encoder.pass_held[0] == (concurrent == 1)  # the request alone: its pass or none


# -- sharing device memory with Warp physics ---------------------------------------------
def test_states_read_on_the_device_equal_the_host_copies(warp_pool):
    """Two Warp physics batches of one task in one process (a Ray engine runs several cells at
    once): each request reads the slots of the batch it names, equal to the host copies."""
    from vabench.tasks import get_task
    from vabench.tasks.task_batch import TaskBatch

    os.environ["VABENCH_WARP_DEVICE"] = "cpu"
    try:
        seeds = verified_seeds(CUBE)[:4]
        first = TaskBatch(get_task(CUBE), 3, backend="mjx", impl="warp")
        second = TaskBatch(get_task(CUBE), 2, backend="mjx", impl="warp")
        assert all(r.ok for r in first.reset(range(3), seeds[:3]))
        assert all(r.ok for r in second.reset(range(2), seeds[3:1:-1]))  # other states, slot 0
        down = {"action": "gripper.move_world", "axis": "z", "sign": "-", "distance_mm": 30}
        first.step([down, None, down])  # slot 1 idles: frozen, its state still the reset's

        def items(tb, slots):
            qpos, p = tb.observe()
            variants = tb.batch.variant()
            out = []
            for slot in slots:
                pose = cam.head_view({"right": p.gc[slot, 0]}, ("right",))
                out.append(RenderItem(qpos[slot], int(variants[slot]), pose, slot=slot))
            return out

        a, b = items(first, (2, 0, 1, 0)), items(second, (0, 1))
        assert warp_pool.shares(first.batch) and warp_pool.shares(second.batch)
        before = warp_pool.stats.shared_state
        shared_a = warp_pool.render_rgb(CUBE, a, SIZE, source=first.batch)
        shared_b = warp_pool.render_rgb(CUBE, b, SIZE, source=second.batch)
        assert warp_pool.stats.shared_state - before == 6
        host_a, host_b = warp_pool.render_rgb(CUBE, a, SIZE), warp_pool.render_rgb(CUBE, b, SIZE)
    finally:
        os.environ.pop("VABENCH_WARP_DEVICE", None)
    assert np.array_equal(shared_a, host_a) and np.array_equal(shared_b, host_b)
    assert not np.array_equal(shared_a[1], shared_b[0])  # slot 0 of each batch: its own state
    assert not np.array_equal(shared_a[0], shared_a[1])  # the slots differ
    assert not warp_pool.shares(object())  # not a Warp batch: host copies


def test_passes_kept_stay_within_the_memory_budget(cube_items, shoe_items, warp_pool):
    """Every task family and request size makes a pass; a sweep meets dozens. The passes kept
    never take more than the budget (least recently used ones go), and an evicted pass rebuilt
    later draws the same pixels."""
    from vabench.render.warp_pass import pass_bytes

    budget = pass_bytes(SIZE.width, SIZE.height, 6, device_jpeg=False)
    os.environ["VABENCH_WARP_DEVICE"] = "cpu"
    try:
        with WarpRenderPool(max_size=(320, 240), max_pass=4, memory_budget=budget) as small:
            first = small.render_rgb(CUBE, cube_items[:3], SIZE)
            for n in (1, 2, 4, 3):
                small.render_rgb(SHOE, shoe_items[:n], SIZE)
                assert small.bytes_kept() <= budget
            assert small.stats.evicted >= 2
            assert small.stats.built == 4  # 3 images drawn in the kept pass of 4 worlds
            # the builds' time (the device's lock held: every batch waits) is kept
            assert 0 < small.stats.build_s < small.stats.wall_s
            again = small.render_rgb(CUBE, cube_items[:3], SIZE)  # its pass was evicted
            assert small.bytes_kept() <= budget
    finally:
        os.environ.pop("VABENCH_WARP_DEVICE", None)
    assert np.array_equal(first, again)
    assert np.array_equal(first, warp_pool.render_rgb(CUBE, cube_items[:3], SIZE))


# -- in the engine -----------------------------------------------------------------------
def _model_images(run) -> list[np.ndarray]:
    from tests.engine_util import body_json

    frames = []
    for _, raw in run.bodies:
        body = body_json(raw)
        for message in body.get("messages", []):
            for part in message.get("content", []) if isinstance(message, dict) else []:
                if isinstance(part, dict) and part.get("type") == "image_url":
                    b64 = part["image_url"]["url"].split(",", 1)[1]
                    frames.append(_decode(base64.b64decode(b64)))
    return frames


@pytest.mark.parametrize("physics", ["c", "warp"])
def test_an_episode_sees_warp_images(warp_pool, physics):
    """Passive protocol through the engine and the embedded server: every observation is the
    five views, drawn by the Warp renderer; with Warp physics the renderer reads the states in
    the physics batch's memory."""
    from tests.engine_util import STOP, move, run_scripted

    kwargs = {"backend": "mjx", "impl": "warp", "device": "cpu"} if physics == "warp" else {}
    before = warp_pool.stats.shared_state
    run = run_scripted(
        CUBE, [move("z", "-", 20), STOP], warp_pool, protocol="passive", budget=3, **kwargs
    )
    assert run.result.status in ("success", "failure"), run.result.error
    frames = _model_images(run)
    assert len(frames) >= 10 and all(f.shape == (120, 160, 3) for f in frames)
    shared = warp_pool.stats.shared_state - before
    assert shared == (10 if physics == "warp" else 0)  # reset and one action, five views each


def test_concurrent_requests_get_their_own_images(warp_pool, cube_items, shoe_items):
    """Two tasks' render services ask at once (as in a sweep): JPEG encoding of one request
    overlaps the next request's pass, and no image is overwritten or swapped."""
    from concurrent.futures import ThreadPoolExecutor

    alone = {CUBE: warp_pool.render(CUBE, cube_items, SIZE)}
    alone[SHOE] = warp_pool.render(SHOE, shoe_items, SIZE)
    jobs = [(CUBE, cube_items), (SHOE, shoe_items)] * 3
    with ThreadPoolExecutor(2) as threads:
        got = list(threads.map(lambda job: warp_pool.render(job[0], job[1], SIZE), jobs))
    for (task, _), images in zip(jobs, got, strict=True):
        assert images == alone[task]


def _cuda() -> bool:
    import warp as wp

    return wp.is_cuda_available()


@pytest.mark.skipif(not _cuda(), reason="no JPEG extra on a GPU (run on the GPU host)")
def test_a_gpu_host_without_nvimagecodec_is_told_what_it_costs(monkeypatch, caplog):
    """Issue 34: on a GPU host without the JPEG extra, images were encoded on CPU threads at
    about the GL pool's rate with nothing said; the renderer's first lines now name the extra
    and the measured cost."""
    from vabench.render import gpu_jpeg, nvjpeg, warp_renderer

    monkeypatch.setattr(gpu_jpeg, "available", lambda: False)
    monkeypatch.setattr(nvjpeg, "available", lambda: False)
    monkeypatch.setattr(warp_renderer.wp, "load_module", _no_module)  # nor our kernels
    with caplog.at_level("WARNING"), WarpRenderPool(device="cuda:0", max_size=(64, 48)) as pool:
        assert "threads" in (pool.info or "")
    assert any("JPEG kernels do not load" in r.getMessage() for r in caplog.records)
    assert any(
        "vabench[jpeg-cu13]" in r.getMessage() and "images/s" in r.getMessage()
        for r in caplog.records
    )


def _no_module(*args, **kwargs):
    raise RuntimeError("NVRTC: compilation failed (made up by the test)")


@pytest.mark.skipif(not _cuda(), reason="the GPU's default JPEG (run on the GPU host)")
def test_a_gpu_encodes_in_the_renderers_own_kernels_by_default(monkeypatch):
    """auto on a GPU: each pass's own Warp JPEG kernels (faster in the suite than nvJPEG:
    docs/PERFORMANCE.md, "JPEG on the GPU")."""
    monkeypatch.delenv("VABENCH_WARP_JPEG", raising=False)
    with WarpRenderPool(device="cuda:0", max_size=(64, 48)) as pool:
        assert pool.jpeg == "auto" and "Warp kernels" in (pool.info or "")
        assert pool._jpeg_kind == "kernels"


def test_jpeg_kernels_asked_for_but_not_loading_is_one_clear_error(monkeypatch):
    """jpeg="kernels" where they cannot load (a compiler error) names the choice, and does not
    fall back behind the user's back (auto does: the GPU test above and the one before it)."""
    from vabench.render import warp_renderer

    monkeypatch.setattr(warp_renderer.wp, "load_module", _no_module)
    pool = WarpRenderPool(device="cpu", max_size=(64, 48), jpeg="kernels")
    with pytest.raises(RenderError, match=r"jpeg='kernels'.*do not load.*NVRTC"):
        pool.start()
    pool.close()


def test_a_pass_s_idle_worlds_look_at_the_sky(cube_items):
    """A pass is up to a third larger than its request (`pass_size`) and ray traces every
    world: the idle ones look straight up from above the scene, so that no ray of theirs hits
    anything (an idle camera at the origin looking down hit the floor in every pixel and cast
    its shadow rays through the scene)."""
    import math

    import mujoco

    from vabench.render.warp_pass import IDLE_CAMERA_HEIGHT, RenderPass, render_models
    from vabench.tasks import get_task

    os.environ["VABENCH_WARP_DEVICE"] = "cpu"
    try:
        import warp as wp

        models = render_models(get_task(CUBE), SIZE.width, SIZE.height)
        with wp.ScopedDevice("cpu"):
            p = RenderPass(models, 3, SIZE.width, SIZE.height, device_jpeg=False)
            p.draw(cube_items[:2], None)
            wp.synchronize()
            xpos, xmat = p.d.cam_xpos.numpy()[:, p.cam], p.d.cam_xmat.numpy()[:, p.cam]
    finally:
        os.environ.pop("VABENCH_WARP_DEVICE", None)
    np.testing.assert_allclose(xpos[:2], [it.camera.pos for it in cube_items[:2]], atol=1e-5)
    assert xpos[2][2] == IDLE_CAMERA_HEIGHT
    m = models[0]
    d = mujoco.MjData(m)
    d.qpos[:] = cube_items[0].qpos
    mujoco.mj_forward(m, d)
    half = math.tan(math.radians(45.0) / 2)
    aspect = SIZE.width / SIZE.height
    geom = np.zeros(1, np.int32)
    for sx in (-1, 0, 1):
        for sy in (-1, 0, 1):
            view = xmat[2] @ np.array([sx * half * aspect, sy * half, -1.0])
            assert view[2] > 0  # up
            hit = mujoco.mj_ray(m, d, xpos[2].astype(float), view.astype(float), None, 1, -1, geom)
            assert hit < 0, f"an idle world's ray ({sx}, {sy}) hits geom {geom[0]}"
    # a ray of an item's own camera does hit the scene (the check above can fail)
    centre = xmat[0] @ np.array([0.0, 0.0, -1.0])
    assert mujoco.mj_ray(m, d, xpos[0].astype(float), centre.astype(float), None, 1, -1, geom) > 0


def test_the_scene_bvh_rebuilt_at_the_first_pose_changes_no_pixel(shoe_items):
    """A pass builds its scene BVH again around its first items (MuJoCo Warp builds it at qpos0,
    every free object at the origin, then only refits it: slower rays, measured on an H100).
    The rebuilt tree must draw the same images as the refit one, on the first draw and on a
    later one of other states, and be a new tree (the check of pixels can fail: a tree whose
    worlds' roots were not recomputed draws other worlds' geoms or none)."""
    import warp as wp

    from vabench.render.warp_pass import RENDER_BLOCK_DIM, RenderPass, render_models
    from vabench.tasks import get_task

    models = render_models(get_task(SHOE), SIZE.width, SIZE.height)
    later = _items(SHOE, verified_seeds(SHOE)[2])[:4]
    images = {}
    with wp.ScopedDevice("cpu"):
        for rebuilt in (False, True):
            p = RenderPass(models, 4, SIZE.width, SIZE.height, device_jpeg=False)
            assert p.m.block_dim.render == RENDER_BLOCK_DIM
            p._bvh_posed = not rebuilt  # False: the pass rebuilds on its first draw
            first_id = p.rc.bvh_id
            p.draw(shoe_items, None)
            wp.synchronize()
            assert (p.rc.bvh_id != first_id) == rebuilt
            first = p.rc.rgb_data.numpy().copy()
            p.draw(later, None)
            wp.synchronize()
            images[rebuilt] = (first, p.rc.rgb_data.numpy().copy())
    for before, after in zip(images[False], images[True], strict=True):
        assert before.any()
        assert np.mean(before != after) < 1e-4


def test_by_default_states_come_from_the_host_copies(cube_items):
    """A request naming its Warp physics batch is drawn from the host copies its items carry
    unless the pool reads states on the device (`state_on_device`): the device gather waits
    behind every action queued on the batch's stream. Same images either way."""
    from vabench.tasks import get_task
    from vabench.tasks.task_batch import TaskBatch

    os.environ["VABENCH_WARP_DEVICE"] = "cpu"
    try:
        tb = TaskBatch(get_task(CUBE), 2, backend="mjx", impl="warp")
        assert all(r.ok for r in tb.reset(range(2), verified_seeds(CUBE)[:2]))
        qpos, p = tb.observe()
        variants = tb.batch.variant()
        items = [
            RenderItem(
                qpos[s], int(variants[s]), cam.head_view({"right": p.gc[s, 0]}, ("right",)), slot=s
            )
            for s in (1, 0)
        ]
        images = {}
        for on_device in (False, True):
            with WarpRenderPool(max_size=(320, 240), state_on_device=on_device) as pool:
                assert pool.shares(tb.batch)
                images[on_device] = pool.render_rgb(CUBE, items, SIZE, source=tb.batch)
                assert pool.stats.shared_state == (2 if on_device else 0)
    finally:
        os.environ.pop("VABENCH_WARP_DEVICE", None)
    for host, device in zip(images[False], images[True], strict=True):
        np.testing.assert_array_equal(host, device)


def test_a_family_s_variant_fields_are_found_once_for_all_its_passes(shoe_items, monkeypatch):
    """Comparing a family's object variants (a model on the device per variant) was most of a
    pass's build, and a pass is built per family and size (42 a process in the warm suite on an
    H100): the renderer does it once a family; passes of other sizes reuse it, pixel for pixel
    as a pass that found the fields itself."""
    from vabench.render import warp_renderer
    from vabench.sim_mjx.warp import model

    calls: list[str] = []

    def counted(models, ignore=model.PHYSICS_IGNORED):
        calls.append(ignore)
        return model.variant_fields(models, ignore)

    monkeypatch.setattr(warp_renderer, "variant_fields", counted)
    monkeypatch.setenv("VABENCH_WARP_DEVICE", "cpu")
    with WarpRenderPool(max_size=(320, 240), jpeg="host") as pool:
        four = pool.render_rgb(SHOE, shoe_items, SIZE)  # a pass of 4 worlds
        one = pool.render_rgb(SHOE, shoe_items[2:3], SIZE)  # a pass of 1 (4 serves up to 2)
        assert pool.stats.built == 2
    assert calls == [model.RENDER_IGNORED]
    assert np.array_equal(four[2:3], one)
    assert len({it.variant for it in shoe_items}) > 1  # the fields do differ between them
