"""Demonstration videos: seeds apart from evaluation, clean deterministic frames, the scene
they start from, a real cache."""

from __future__ import annotations

import io
import json
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from PIL import Image

from vabench.agent.visibility import filter_proprio
from vabench.demos import build, store
from vabench.render.worker import ImageSettings
from vabench.sim_mjx.layout import proprio_fields
from vabench.tasks import BASE_FAMILIES, get_task
from vabench.tasks.task_batch import TaskBatch, run_experts

SMALL = ImageSettings(160, 120, 80)
FAMILIES = ("click_bell_right", "grasp_single_bottle_upright")  # the two shortest experts
META_KEYS = {
    "version", "task", "seed", "n_frames", "fps", "width", "height", "quality", "sha256", "key",
    "renderer", "expert_steps", "rejected",
}  # fmt: skip
MANIFEST_KEYS = {
    "version", "task", "demo_seed", "candidates", "rejected", "expert_steps", "frames", "fps",
    "width", "height", "quality", "sha256", "renderer",
}  # fmt: skip


def _markers(jpeg: bytes) -> list[int]:
    """JPEG segment markers up to the start of scan."""
    out, i = [], 2
    while i + 4 <= len(jpeg) and jpeg[i] == 0xFF:
        marker = jpeg[i + 1]
        out.append(marker)
        if marker == 0xDA:
            break
        i += 2 + int.from_bytes(jpeg[i + 2 : i + 4], "big")
    return out


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    cache = tmp_path_factory.mktemp("demos")
    infos = {t: build.build_demo(t, cache, settings=SMALL, mp4=False) for t in FAMILIES}
    return cache, infos


def test_committed_demo_seeds_are_never_evaluation_seeds():
    manifests = store.load_manifests()
    assert set(manifests) == set(BASE_FAMILIES), "a demo manifest per base family"
    evaluation = build.evaluation_seeds()
    assert evaluation, "configs/seeds holds the evaluation manifests"
    for task, doc in manifests.items():
        assert set(doc) == MANIFEST_KEYS, task
        assert doc["demo_seed"] not in evaluation, task
        assert 0 <= doc["demo_seed"] < 1000, task
        assert not set(map(int, doc["rejected"])) & evaluation, task
        assert 15 <= doc["frames"] <= 110, (task, doc["frames"])  # FACTS 30-110; see build
        assert doc["frames"] == 1 + build.FRAMES_PER_ACTION * doc["expert_steps"], task
        # the reference's video size (PROTOCOL_FACTS 6.5), the size the builder uses
        assert (doc["width"], doc["height"]) == (1280, 960), task
        settings = build.DEMO_SETTINGS
        assert (doc["width"], doc["height"], doc["quality"]) == (
            settings.width,
            settings.height,
            settings.quality,
        ), task


def test_candidates_skip_every_excluded_seed():
    evaluation = build.evaluation_seeds()
    excluded = evaluation | {999, 997}
    order = list(build.demo_candidates(excluded))
    assert order[:2] == [998, 996]
    assert not set(order) & excluded
    assert all(0 <= s < 1000 for s in order)
    # a manifest that retained seeds below 1000 would be skipped too
    assert 500 not in list(build.demo_candidates({500}))


def test_built_demo_seeds_and_frames(built):
    cache, infos = built
    evaluation = build.evaluation_seeds()
    for task, info in infos.items():
        assert info.seed not in evaluation
        demo = store.load_demo(task, cache)
        assert demo.n_frames == info.n_frames == 1 + build.FRAMES_PER_ACTION * info.expert_steps
        assert 15 <= demo.n_frames <= 110
        for jpeg in demo.frames:
            assert jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9"
            with Image.open(io.BytesIO(jpeg)) as im:
                assert (im.format, im.mode, im.size) == ("JPEG", "RGB", (160, 120))
        # the robot moves: first and last frames differ
        assert demo.frames[0] != demo.frames[-1]


def test_rebuild_is_deterministic_and_cache_skips_work(built, monkeypatch):
    cache, infos = built
    task = FAMILIES[0]
    before = store.load_demo(task, cache).frames
    again = build.build_demo(task, cache, settings=SMALL, mp4=False, force=True)
    assert again == infos[task]
    assert store.load_demo(task, cache).frames == before

    def no_work(*args, **kwargs):
        raise AssertionError("a current cache must not simulate again")

    monkeypatch.setattr(build, "record", no_work)
    assert build.build_demo(task, cache, settings=SMALL, mp4=False) == infos[task]
    # other settings are another key: the cache is not current for them
    with pytest.raises(AssertionError, match="must not simulate"):
        build.build_demo(task, cache, settings=ImageSettings(160, 120, 70), mp4=False)


def test_stored_data_has_no_evaluator_numbers(built):
    cache, infos = built
    for task, info in infos.items():
        root = store.task_dir(task, cache)
        meta = json.loads((root / "meta.json").read_text())
        assert set(meta) == META_KEYS
        # only scalars and the candidates' reasons: no poses, joints, actions or phases
        assert all(isinstance(v, (int, float, str, dict)) for v in meta.values())
        assert all(isinstance(v, str) for v in meta["rejected"].values())
        names = sorted(p.name for p in (root / "frames").iterdir())
        assert names == [f"{k:04d}.jpg" for k in range(info.n_frames)]
        assert sorted(p.name for p in root.iterdir()) == ["frames", "meta.json", "scene.json"]
        demo = store.load_demo(task, cache)
        # the scene holds the robot's visible fields and nothing else (no object, no seed)
        scene = json.loads((root / "scene.json").read_text())
        assert set(scene) == {"robot"}
        arms = get_task(task).arms
        assert filter_proprio(scene["robot"], arms) == scene["robot"] == demo.robot
        for jpeg in demo.frames:
            # no comment (COM) or EXIF/XMP (APP1+) segments: pixels only
            assert not {0xFE, *range(0xE1, 0xF0)} & set(_markers(jpeg))
        n = demo.n_frames
        assert demo.frame_label(n - 1) == f"frame {n - 1} of {n}"
        assert str(info.seed) not in demo.frame_label(0)


def test_the_scene_is_the_reset_of_the_demo_seed(built):
    """The robot state stored with a demo is what a fresh reset at its seed shows (frame 0 is
    that reset seen from the head camera: `test_learning_scene.py` compares both with an
    evaluation episode's first observation)."""
    cache, infos = built
    for task, info in infos.items():
        tb = TaskBatch(get_task(task), 1, backend="c")
        assert tb.reset([0], [info.seed])[0].ok
        fresh = proprio_fields(tb.observe()[1], 0, tb.batch.arms)
        assert store.load_demo(task, cache).robot == fresh, task
        # and not the robot at the end of the demonstration
        run_experts(tb, [info.seed])
        assert proprio_fields(tb.observe()[1], 0, tb.batch.arms) != fresh


def test_load_demo_errors_name_the_fix(built, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"python -m vabench\.demos build --task lift_pot"):
        store.load_demo("lift_pot", tmp_path)
    cache, _ = built
    task = FAMILIES[1]
    frame = store.task_dir(task, cache) / "frames" / "0001.jpg"
    good = frame.read_bytes()
    frame.write_bytes(good[:-10] + b"\x00" * 8 + good[-2:])
    try:
        with pytest.raises(ValueError, match="sha256"):
            store.load_demo(task, cache)
    finally:
        frame.write_bytes(good)
    scene = store.task_dir(task, cache) / "scene.json"
    kept = scene.read_bytes()
    scene.unlink()
    try:
        with pytest.raises(ValueError, match=r"scene\.json: missing or unreadable; rebuild"):
            store.load_demo(task, cache)
    finally:
        scene.write_bytes(kept)
    with pytest.raises(ValueError, match="unknown task 'no_such'"):
        build.build_demo("no_such", cache)


def test_capture_off_by_default_and_changes_no_result():
    task = get_task("click_bell_right")
    finals = []
    for capture in (0, 50):
        tb = TaskBatch(task, 1, backend="c")
        assert tb.batch.capture_every == 0
        tb.batch.capture_every = capture
        ep = run_experts(tb, [999])[0]
        assert ep.success
        finals.append(tb.batch.qpos()[0])
        captured = tb.batch.captured.get(0, [])
        assert len(captured) == (ep.steps * (tb.batch.n_substeps // 50) if capture else 0)
    np.testing.assert_array_equal(finals[0], finals[1])


def test_source_digest_is_stable():
    assert build.source_digest() == build.source_digest()


def test_concurrent_builds_of_a_missing_demo_simulate_once(tmp_path, monkeypatch):
    calls = []
    real = build.record

    def counted(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(build, "record", counted)
    task = FAMILIES[0]
    with ThreadPoolExecutor(2) as ex:
        infos = list(
            ex.map(lambda _: build.build_demo(task, tmp_path, settings=SMALL, mp4=False), range(2))
        )
    assert calls == [task]
    assert infos[0] == infos[1]
