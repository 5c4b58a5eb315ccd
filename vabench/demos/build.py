"""Building a family's demonstration: choose the seed, run the expert, render the head camera.

Seed: candidates 999, 998, ... down to 0 (below the evaluation range, which starts at 1000),
skipping every seed retained by ANY evaluation manifest in `configs/seeds`; the first candidate
whose reset passes the settle gate and whose expert succeeds (C backend) is the demo seed.

Frames: the reset state, then `FRAMES_PER_ACTION` frames inside every executed action (qpos
captured by `CpuBatch.capture_every` every n_substeps // 3 physics steps: at 200 substeps of
4 ms, after steps 66, 132 and 198, so the third is 8 ms before the action's end). An action is
0.8 s of simulated time, so that is 3.75 frames per second of simulated time, and the MP4 plays
at that rate (real time). Counts are 1 + 3 x expert actions: 19 (click_bell_right, 6 actions) to
88 (handover_horizontal_block, 29). FACTS' 30-110 comes from the reference,
whose actions last longer; no uniform rate fits that range with our 0.8 s actions, so the rate
follows the spec's "about 3 per second" and the shortest families have fewer frames.

Every frame is drawn from the head camera of the reset state (`camera.head_view`; it does not
move) by the RenderPool's clean model path: RGB JPEG, no overlays, nothing else in the image.
Frames are 1280x960 q90, the reference's video size (and the sweep's default model image), so
frame 0 is the head-camera image an evaluation episode at the demo seed starts from. The
robot state of that reset, in the model-visible fields, is stored beside the frames: the
learning stage shows the scene's first observation from it (`agent.demonstration`).

Cache: `cache_key` hashes everything that decides the frames (format version, task, image
settings, frame rule, MuJoCo version, the evaluation seeds the scan must avoid, and the source
of the simulator, tasks, renderer and this package plus the assets). A build whose key matches
the cached meta.json and whose frames match their hash does no work.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from vabench.demos import store
from vabench.render import camera as cam
from vabench.render.worker import ImageSettings, RenderItem, RenderPool
from vabench.sim_mjx import robot_constants as rc
from vabench.sim_mjx.cpu import CpuBatch
from vabench.sim_mjx.layout import proprio_fields
from vabench.tasks import REGISTRY
from vabench.tasks import manifests as seed_manifests
from vabench.tasks.task_batch import TaskBatch, run_experts

log = logging.getLogger(__name__)

DEMO_SETTINGS = ImageSettings(1280, 960, 90)  # the reference's demo videos (PROTOCOL_FACTS 6.5)
FRAMES_PER_ACTION = 3
FPS = FRAMES_PER_ACTION / rc.ACTION_SECONDS  # 3.75 frames per second of simulated time
FIRST_CANDIDATE = 999  # scanned downwards: evaluation seeds start at 1000
CANDIDATES_RULE = "999 downward, skipping every seed retained by any evaluation manifest"
MAX_CANDIDATES = 40
_SOURCE_PARTS = ("vabench/sim_mjx", "vabench/tasks", "vabench/render", "vabench/demos", "assets")


class DemoError(RuntimeError):
    """No demonstration could be built (no candidate succeeded, or the renderer failed)."""


def evaluation_seeds(directory: Path = seed_manifests.MANIFEST_DIR) -> set[int]:
    """Every seed retained by any evaluation manifest (all families, base and variants)."""
    out: set[int] = set()
    for path in sorted(Path(directory).glob("*.json")):
        out.update(int(s) for s in json.loads(path.read_text()).get("retained", []))
    return out


def demo_candidates(excluded: set[int], start: int = FIRST_CANDIDATE) -> Iterator[int]:
    """Demo seed candidates in scan order: start, start-1, ... 0, never one in `excluded`."""
    for seed in range(start, -1, -1):
        if seed not in excluded:
            yield seed


def source_digest(root: Path = store.REPO_ROOT) -> str:
    """sha256 over the files that decide what the expert does and how frames look."""
    h = hashlib.sha256()
    for part in _SOURCE_PARTS:
        for path in sorted((root / part).rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                h.update(str(path.relative_to(root)).encode())
                h.update(path.read_bytes())
    return h.hexdigest()


def cache_key(task: str, settings: ImageSettings, excluded: set[int]) -> str:
    doc = {
        "format": store.FORMAT_VERSION,
        "task": task,
        "image": [settings.width, settings.height, settings.quality],
        "frames_per_action": FRAMES_PER_ACTION,
        "first_candidate": FIRST_CANDIDATE,
        "excluded": sorted(excluded),
        "mujoco": mujoco.__version__,
        "source": source_digest(),
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


@dataclass
class Rollout:
    """One successful expert execution, evaluator-side: states to render, never to show."""

    seed: int
    variant: int
    states: list[np.ndarray]  # qpos: the reset state, then the captured ones in order
    camera: cam.CameraPose
    robot: dict[str, dict[str, Any]]  # model-visible robot state at the reset
    steps: int
    rejected: dict[int, str]


def record(task_name: str, excluded: set[int], max_candidates: int = MAX_CANDIDATES) -> Rollout:
    """Scan candidates (see `demo_candidates`) and capture the first successful expert run."""
    task = REGISTRY[task_name]
    tb = TaskBatch(task, 1, backend="c")
    batch = tb.batch
    assert isinstance(batch, CpuBatch)
    rejected: dict[int, str] = {}
    for n, seed in enumerate(demo_candidates(excluded)):
        if n >= max_candidates:
            break
        batch.capture_every, batch.captured = 0, {}
        # run_experts resets again, identically: this reset only gives the head camera's target.
        if not tb.reset([0], [seed])[0].ok:
            rejected[seed] = "rejected at reset"
            continue
        view = tb.views([0])[0]
        head = cam.head_view({arm: view.arms[arm].gc for arm in task.arms}, task.arms)
        robot = proprio_fields(tb.observe()[1], 0, batch.arms)
        batch.capture_every = batch.n_substeps // FRAMES_PER_ACTION
        ep = run_experts(tb, [seed])[0]
        batch.capture_every = 0
        if not ep.success:
            rejected[seed] = ep.end
            continue
        states = [np.array(tb.init_qpos[0]), *batch.captured.get(0, [])]
        return Rollout(seed, int(batch.variant()[0]), states, head, robot, ep.steps, rejected)
    raise DemoError(f"{task_name}: no demo seed among {len(rejected)} candidates: {rejected}")


def render_frames(
    task_name: str, rollout: Rollout, settings: ImageSettings, pool: RenderPool
) -> list[bytes]:
    items = [RenderItem(q, rollout.variant, rollout.camera) for q in rollout.states]
    return pool.render(task_name, items, settings)


def write_mp4(frames: list[bytes], path: Path, fps: float) -> bool:
    """Encode the JPEG frames as H.264 MP4; False (nothing written) without imageio-ffmpeg."""
    try:
        import imageio_ffmpeg
    except ImportError:
        return False
    import io

    from PIL import Image

    first = Image.open(io.BytesIO(frames[0]))
    writer = imageio_ffmpeg.write_frames(
        str(path), first.size, fps=fps, codec="libx264", quality=8, macro_block_size=16
    )
    writer.send(None)
    for jpeg in frames:
        writer.send(np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")).tobytes())
    writer.close()
    return True


def _current(task_name: str, cache_dir: Path, key: str) -> store.DemoInfo | None:
    info = store.read_info(task_name, cache_dir)
    if info is None or info.key != key:
        return None
    try:
        store.load_demo(task_name, cache_dir)
    except (OSError, ValueError):
        return None
    return info


def build_demo(
    task_name: str,
    cache_dir: Path | None = None,
    *,
    settings: ImageSettings = DEMO_SETTINGS,
    pool: RenderPool | None = None,
    force: bool = False,
    mp4: bool = True,
    seeds_dir: Path = seed_manifests.MANIFEST_DIR,
) -> store.DemoInfo:
    """Build (or find current in the cache) the demonstration of `task_name`.

    Returns the cached info without simulating or rendering when the cache key matches and the
    frames check out, unless `force`. `pool` renders when given (a CLI building many families
    shares one); otherwise a one-worker pool is started for this call. `cache_dir`: the
    user's cache (`store.default_cache`) unless given.
    """
    cache_dir = cache_dir or store.default_cache()
    if task_name not in REGISTRY:
        raise ValueError(f"task: unknown task {task_name!r}; valid tasks: {sorted(REGISTRY)}")
    excluded = evaluation_seeds(seeds_dir)
    key = cache_key(task_name, settings, excluded)
    Path(cache_dir).mkdir(parents=True, exist_ok=True)
    # Sweep processes may build the same missing demo at once: one builds, the others wait
    # and then find the cache current.
    with open(Path(cache_dir) / f"{task_name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not force and (info := _current(task_name, cache_dir, key)) is not None:
            log.info("%s: demo cache current (%d frames)", task_name, info.n_frames)
            return info
        return _build(task_name, cache_dir, key, excluded, settings, pool, mp4)


def _build(
    task_name: str,
    cache_dir: Path,
    key: str,
    excluded: set[int],
    settings: ImageSettings,
    pool: RenderPool | None,
    mp4: bool,
) -> store.DemoInfo:
    rollout = record(task_name, excluded)
    if pool is None:
        with RenderPool(workers=1, max_size=(settings.width, settings.height)) as own:
            frames = render_frames(task_name, rollout, settings, own)
            renderer = str(own.gl_info)
    else:
        frames = render_frames(task_name, rollout, settings, pool)
        renderer = str(pool.gl_info)
    info = store.DemoInfo(
        task=task_name,
        seed=rollout.seed,
        n_frames=len(frames),
        fps=FPS,
        width=settings.width,
        height=settings.height,
        quality=settings.quality,
        sha256=store.frames_digest(frames),
        key=key,
        renderer=renderer,
        expert_steps=rollout.steps,
        rejected=rollout.rejected,
    )
    root = store.write_demo(info, frames, rollout.robot, cache_dir)
    video = root / "demo.mp4"
    video.unlink(missing_ok=True)
    if mp4 and not write_mp4(frames, video, FPS):
        log.info("%s: no MP4 (install the `demos` extra for imageio-ffmpeg)", task_name)
    return info
