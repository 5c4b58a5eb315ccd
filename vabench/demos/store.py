"""The demonstration cache and the committed demo manifests.

Cache (regenerated on demand, never committed; default `.cache/demos`, gitignored):

    <cache_dir>/<task>/meta.json      DemoInfo (evaluator-side bookkeeping, seed included)
    <cache_dir>/<task>/frames/NNNN.jpg  the frames, in order (clean RGB JPEG, nothing else)
    <cache_dir>/<task>/scene.json     {"robot": ...}: the robot state at the reset, in the
                                      model-visible fields of every observation (`proprio_fields`)
    <cache_dir>/<task>/demo.mp4       the same frames as a video, when an encoder is installed

Manifest (committed): `configs/demos/<task>.json`, the demo seed, how it was chosen, the frame
count, rate, resolution and the frames' content hash. Demo seeds are kept apart from the
evaluation manifests (`configs/seeds`): they are never in any family's retained list.

What a model may see is the frames, "frame k of N" and the scene: frame 0 (the reset seen from
the head camera) with the robot state an evaluation episode's first observation shows at that
seed (`Demo.robot`); `DemoInfo` (seed, hash, key) stays on the evaluator's side.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from vabench import machine_cache
from vabench.sim_mjx import robot_constants as rc

REPO_ROOT = rc.ASSETS.parent
MANIFEST_DIR = REPO_ROOT / "configs" / "demos"
FORMAT_VERSION = 2
"""1: frames and meta.json; 2: scene.json too (the reset's visible robot state)."""
SCENE_FILE = "scene.json"


def default_cache() -> Path:
    """Where demonstrations are cached unless a config says otherwise: the user's cache
    (`XDG_CACHE_HOME`, else ~/.cache), shared by every sweep, checkout and Ray engine of the
    machine; an entry is current only for the code and settings that built it."""
    return machine_cache.cache_dir() / "demos"


@dataclass(frozen=True)
class DemoInfo:
    """One built demonstration (evaluator-side: never put into a prompt)."""

    task: str
    seed: int  # the demonstration seed: below 1000, never an evaluation seed
    n_frames: int
    fps: float  # frames per second of simulated time (also the MP4's playback rate)
    width: int
    height: int
    quality: int
    sha256: str  # of the frames' bytes, in order (see `frames_digest`)
    key: str  # cache key: inputs that determine the frames (see build.cache_key)
    renderer: str  # the GL renderer that drew the frames (hashes differ across renderers)
    expert_steps: int
    rejected: dict[int, str] = field(default_factory=dict)  # candidates tried before `seed`

    def to_json(self) -> dict[str, Any]:
        doc = asdict(self)
        doc["rejected"] = {str(k): v for k, v in sorted(self.rejected.items())}
        return {"version": FORMAT_VERSION, **doc}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> DemoInfo:
        if doc.get("version") != FORMAT_VERSION:
            raise ValueError(
                f"demo meta: version must be {FORMAT_VERSION}, got {doc.get('version')}"
            )
        body = {k: v for k, v in doc.items() if k != "version"}
        body["rejected"] = {int(k): v for k, v in body.get("rejected", {}).items()}
        return cls(**body)


@dataclass(frozen=True)
class Demo:
    """A demonstration as the tools serve it: the JPEG frames in order, the robot state at
    the reset (model-visible: per arm the fields of `sim_mjx.layout.proprio_fields`), and its
    info."""

    info: DemoInfo
    frames: list[bytes]
    robot: dict[str, dict[str, Any]]

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    def frame_label(self, k: int) -> str:
        """What the model reads about frame k (0-based, as `expert.frame` indexes it)."""
        if not 0 <= k < len(self.frames):
            raise IndexError(f"frame {k} out of range [0, {len(self.frames)})")
        return f"frame {k} of {len(self.frames)}"


def frames_digest(frames: list[bytes]) -> str:
    """sha256 over every frame, each prefixed by its length (order and boundaries count)."""
    h = hashlib.sha256()
    for f in frames:
        h.update(len(f).to_bytes(8, "little"))
        h.update(f)
    return h.hexdigest()


def task_dir(task: str, cache_dir: Path) -> Path:
    return Path(cache_dir) / task


def read_info(task: str, cache_dir: Path) -> DemoInfo | None:
    """The cached info of `task`, or None when there is none or it is unreadable."""
    path = task_dir(task, cache_dir) / "meta.json"
    try:
        return DemoInfo.from_json(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return None


def write_demo(
    info: DemoInfo, frames: list[bytes], robot: dict[str, dict[str, Any]], cache_dir: Path
) -> Path:
    """Store the frames, the scene and then meta.json (last, so a crash leaves no
    current-looking cache)."""
    root = task_dir(info.task, cache_dir)
    (root / "meta.json").unlink(missing_ok=True)
    fdir = root / "frames"
    fdir.mkdir(parents=True, exist_ok=True)
    for old in fdir.glob("*.jpg"):
        old.unlink()
    for k, jpeg in enumerate(frames):
        (fdir / f"{k:04d}.jpg").write_bytes(jpeg)
    (root / SCENE_FILE).write_text(json.dumps({"robot": robot}, indent=1) + "\n")
    (root / "meta.json").write_text(json.dumps(info.to_json(), indent=1) + "\n")
    return root


def load_demo(task_name: str, cache_dir: Path | None = None) -> Demo:
    """The cached demonstration of `task_name`; raises FileNotFoundError naming the command
    that builds it, and ValueError when the frames do not match their recorded hash or the
    scene is unreadable."""
    cache_dir = cache_dir or default_cache()
    info = read_info(task_name, cache_dir)
    if info is None:
        raise FileNotFoundError(
            f"no demonstration of {task_name!r} in {cache_dir}; "
            f"run `python -m vabench.demos build --task {task_name}`"
        )
    fdir = task_dir(task_name, cache_dir) / "frames"
    frames = [(fdir / f"{k:04d}.jpg").read_bytes() for k in range(info.n_frames)]
    if frames_digest(frames) != info.sha256:
        raise ValueError(f"{fdir}: frames do not match meta.json sha256; rebuild {task_name}")
    scene = task_dir(task_name, cache_dir) / SCENE_FILE
    try:
        robot = json.loads(scene.read_text())["robot"]
    except (OSError, ValueError, KeyError, TypeError):
        raise ValueError(f"{scene}: missing or unreadable; rebuild {task_name}") from None
    return Demo(info, frames, robot)


def manifest_doc(info: DemoInfo, candidates: str) -> dict[str, Any]:
    """The committed manifest of one family's demonstration."""
    return {
        "version": FORMAT_VERSION,
        "task": info.task,
        "demo_seed": info.seed,
        "candidates": candidates,
        "rejected": {str(k): v for k, v in sorted(info.rejected.items())},
        "expert_steps": info.expert_steps,
        "frames": info.n_frames,
        "fps": info.fps,
        "width": info.width,
        "height": info.height,
        "quality": info.quality,
        "sha256": info.sha256,
        "renderer": info.renderer,
    }


def write_manifest(doc: dict[str, Any], directory: Path = MANIFEST_DIR) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{doc['task']}.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def read_manifest(task: str, directory: Path = MANIFEST_DIR) -> dict[str, Any] | None:
    """The committed manifest of `task`, or None when there is none of this format version
    (a build replaces a manifest of another version without comparing it)."""
    try:
        doc = json.loads((Path(directory) / f"{task}.json").read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and doc.get("version") == FORMAT_VERSION else None


def load_manifests(directory: Path = MANIFEST_DIR) -> dict[str, dict[str, Any]]:
    """Every committed demo manifest, by task."""
    out = {}
    for path in sorted(Path(directory).glob("*.json")):
        doc = json.loads(path.read_text())
        if doc.get("version") != FORMAT_VERSION or doc.get("task") != path.stem:
            raise ValueError(f"{path}: not a version-{FORMAT_VERSION} demo manifest")
        out[path.stem] = doc
    return out
