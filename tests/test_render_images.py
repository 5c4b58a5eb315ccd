"""The rendering worker: real processes, real off-screen OpenGL (EGL; Mesa llvmpipe here).

Images are made at a reduced size to keep the suite fast; the geometry of every view is the
same at any resolution.
"""

from __future__ import annotations

import io
import os
import signal

import numpy as np
import pytest
from PIL import Image

from vabench.render import camera as cam
from vabench.render.__main__ import reset_state
from vabench.render.debug import DebugOverlays
from vabench.render.worker import ImageSettings, RenderError, RenderItem, RenderPool
from vabench.tasks.manifests import verified_seeds

TASK = "place_single_cube"
SMALL = ImageSettings(width=320, height=240, quality=95)


@pytest.fixture(scope="module")
def pool():
    with RenderPool(workers=2, platform="auto", timeout_s=60) as p:
        yield p


@pytest.fixture(scope="module")
def state():
    seed = verified_seeds(TASK)[0]
    return reset_state(TASK, seed, "c")


def items_for(state, poses):
    qpos, variant, _ = state
    return [RenderItem(qpos, variant, p) for p in poses]


def decode(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"))


def bundle(state):
    _, _, gcs = state
    return [cam.head_view(gcs, ("right",)), *cam.passive_bundle(gcs, ("right",))]


def test_pool_reports_its_platform(pool):
    assert pool.resolved in ("egl", "osmesa")
    assert pool.gl_info is not None and pool.gl_info.renderer


def test_images_are_jpegs_of_the_requested_size_and_every_view_differs(pool, state):
    jpegs = pool.render(TASK, items_for(state, bundle(state)), SMALL)
    assert len(jpegs) == 6
    arrays = [decode(j) for j in jpegs]
    for a in arrays:
        assert a.shape == (240, 320, 3)
        assert a.std() > 10  # not blank
    for i in range(6):
        for j in range(i + 1, 6):
            assert np.abs(arrays[i].astype(int) - arrays[j]).mean() > 5


def test_rendering_is_deterministic_across_workers_and_batch_positions(pool, state):
    poses = bundle(state)
    first = pool.render(TASK, items_for(state, poses), SMALL)
    # Reversed order puts each view on the other worker and at another position in its chunk.
    second = pool.render(TASK, items_for(state, poses[::-1]), SMALL)[::-1]
    singles = [pool.render(TASK, items_for(state, [p]), SMALL)[0] for p in poses[:2]]
    assert first == second
    assert singles == first[:2]


def test_model_images_are_identical_with_debug_overlays_on(pool, state):
    poses = bundle(state)[:3]
    clean = pool.render(TASK, items_for(state, poses), SMALL)
    debug = pool.render_debug(TASK, items_for(state, poses), DebugOverlays.all("step 3"), SMALL)
    again = pool.render(TASK, items_for(state, poses), SMALL)
    assert again == clean  # nothing of the debug path leaks into a model image
    for c, d in zip(clean, debug, strict=True):
        assert np.abs(decode(c).astype(int) - decode(d)).mean() > 0.5  # overlays did show


def test_state_changes_the_image(pool, state):
    qpos, variant, gcs = state
    pose = cam.semantic_view("topdown", gcs, "right")
    moved = qpos.copy()
    moved[-7] += 0.05  # the last free object 5 cm along x
    a, b = pool.render(
        TASK, [RenderItem(qpos, variant, pose), RenderItem(moved, variant, pose)], SMALL
    )
    assert a != b


def test_a_crashed_worker_is_restarted_and_the_request_retried(pool, state):
    items = items_for(state, bundle(state))
    expected = pool.render(TASK, items, SMALL)
    restarts = pool.stats.restarts
    pool.crash_next(0)  # dies on receiving the next request, before answering
    assert pool.render(TASK, items, SMALL) == expected
    assert pool.stats.restarts == restarts + 1
    os.kill(pool.pids[1], signal.SIGKILL)  # dies between requests
    assert pool.render(TASK, items, SMALL) == expected
    assert pool.stats.restarts == restarts + 2


def test_bad_requests_fail_at_once_with_the_reason_and_leave_the_pool_usable(pool, state):
    qpos, variant, gcs = state
    pose = cam.head_view(gcs, ("right",))
    good = RenderItem(qpos, variant, pose)
    with pytest.raises(RenderError, match="qpos has shape"):
        pool.render(TASK, [good, RenderItem(qpos[:-1], variant, pose)], SMALL)
    with pytest.raises(RenderError, match="variant 5 out of range"):
        pool.render(TASK, [good, RenderItem(qpos, 5, pose)], SMALL)
    with pytest.raises(RenderError, match="unknown task"):
        pool.render("no_such_task", [good], SMALL)
    with pytest.raises(RenderError, match="exceeds"):
        pool.render(TASK, [good], ImageSettings(width=4000, height=3000))
    assert len(pool.render(TASK, [good, good], SMALL)) == 2


def test_image_settings_are_validated():
    with pytest.raises(ValueError, match="quality"):
        ImageSettings(quality=0)
    with pytest.raises(ValueError, match="size"):
        ImageSettings(width=0)
    with pytest.raises(ValueError, match="platform"):
        RenderPool(platform="vulkan")
