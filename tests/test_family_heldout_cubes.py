"""The cube held-out variants (grasp_single_cube_heldout, place_single_cube_heldout,
place_cube_in_bowl_heldout, place_cube_on_cube_heldout): ranges of 200 consecutive seeds, the
predicates on constructed states at each threshold, the geometry that differs from each base
family, and a quick expert run. Numbers transcribed from the paper's tables, FACTS and the
variants' docstrings, independently of the modules."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from tests.task_states import StateBuilder
from vabench.tasks import get_task
from vabench.tasks.runner import TaskBatch, run_experts

TABLE_Z = 0.741
SEEDS = range(1000, 1200)
EPS = 1e-9


def _yaw_deg(quat) -> float:
    w, x, y, z = quat
    assert abs(x) < 1e-12 and abs(y) < 1e-12  # resting flat: a pure yaw
    return float(np.degrees(2 * np.arctan2(z, w)))


def _inside(v, lo, hi) -> bool:
    return lo - EPS <= v <= hi + EPS


def _geom(model: mujoco.MjModel, name: str) -> tuple[np.ndarray, np.ndarray, int]:
    """(size, rgba of its material, type) of a named geom."""
    g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
    assert g >= 0, name
    mat = model.geom_matid[g]
    rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
    return model.geom_size[g].copy(), rgba.copy(), int(model.geom_type[g])


def _differs_from_base(name: str, base: str, objects: list[str]) -> None:
    """Variant seeds give other scenes than the same seeds of the base family."""
    var, ref = get_task(name), get_task(base)
    for seed in range(1000, 1020):
        a, b = var.sample(seed).poses, ref.sample(seed).poses
        for obj in objects:
            assert not np.allclose(a[obj][0], b[obj][0]), (seed, obj)


def _expert_quick(name: str, seeds: list[int]) -> None:
    task = get_task(name)
    tb = TaskBatch(task, len(seeds), backend="c")
    for ep in run_experts(tb, seeds):
        assert ep.success, (ep.seed, ep.end, ep.last_checks)
        assert ep.steps <= task.step_budget
        progress = [a["progress"] for a in ep.actions]
        assert progress == sorted(progress) and progress[-1] == len(task.checkpoints)


def _transfer_fields(name: str, base: str) -> None:
    task, ref = get_task(name), get_task(base)
    assert task.suite == "transfer" and task.base_family == base
    assert task.instruction == ref.instruction
    assert (task.arms, task.step_budget, task.checkpoints) == (
        ref.arms,
        ref.step_budget,
        ref.checkpoints,
    )


# == grasp_single_cube_heldout ==================================================================
GSC = "grasp_single_cube_heldout"
RED_BOX_HALF = (0.02, 0.03, 0.0225)  # 40 x 60 x 45 mm
DISTRACTORS = ("distractor_blue", "distractor_yellow", "distractor_green")


def test_grasp_heldout_samples_in_range():
    task = get_task(GSC)
    for seed in SEEDS:
        poses = task.sample(seed).poses
        pos, quat = poses["cube"]
        assert _inside(pos[0], 0.18, 0.26) and _inside(pos[1], -0.16, -0.06), seed
        assert pos[2] == pytest.approx(TABLE_Z + RED_BOX_HALF[2])
        assert _inside(_yaw_deg(quat), -45.0, 45.0), seed
        for name in DISTRACTORS:
            d, dq = poses[name]
            assert _inside(np.linalg.norm(d[:2] - pos[:2]), 0.11, 0.17), (seed, name)
            assert _inside(_yaw_deg(dq), -90.0, 90.0), (seed, name)
        for i, a in enumerate(DISTRACTORS):
            for b in DISTRACTORS[i + 1 :]:
                gap = np.linalg.norm(poses[a][0][:2] - poses[b][0][:2])
                assert gap >= 0.09 - EPS, (seed, a, b)


def test_grasp_heldout_geometry_differs_from_base():
    _transfer_fields(GSC, "grasp_single_cube")
    model = get_task(GSC).build_model(0)
    base = get_task("grasp_single_cube").build_model(0)
    size, rgba, _ = _geom(model, "cube_box")
    base_size, base_rgba, _ = _geom(base, "cube_box")
    np.testing.assert_allclose(size, RED_BOX_HALF)
    np.testing.assert_allclose(base_size, [0.025] * 3)
    assert not np.allclose(np.sort(size), np.sort(base_size))  # a held-out box, not the cube
    np.testing.assert_allclose(rgba, base_rgba)  # still "the red one" of the instruction
    seen = []
    for name in DISTRACTORS:
        d_size, d_rgba, _ = _geom(model, f"{name}_box")
        assert not np.allclose(np.sort(d_size), np.sort(size)), name  # other sizes
        assert np.abs(d_rgba[:3] - rgba[:3]).max() > 0.4, name  # other colours: not red
        assert not (d_rgba[0] > 0.6 and d_rgba[1] < 0.4 and d_rgba[2] < 0.4), name
        seen.append(tuple(np.round(d_rgba, 3)))
    assert len(set(seen)) == 3  # three distinct colours
    # each distractor is clear of the open fingers around the red box (90 mm aperture, 12 mm
    # fingers): centre distance >= 110 mm > 51 mm + the distractor's largest half-diagonal
    for name in DISTRACTORS:
        d_size, _, _ = _geom(model, f"{name}_box")
        assert 0.045 + 0.006 + np.linalg.norm(d_size[:2]) < 0.11
    _differs_from_base(GSC, "grasp_single_cube", ["cube"])


@pytest.mark.parametrize(
    ("lift", "closed", "ok"),
    [(0.0505, True, True), (0.0495, True, False), (0.0505, False, False), (0.20, True, True)],
)
def test_grasp_heldout_predicate(lift, closed, ok):
    b = StateBuilder(get_task(GSC))
    b.move("cube", [0.0, 0.0, lift]).grip("right", not closed)
    ev = b.evaluate()
    assert bool(ev.success) is ok
    assert bool(ev.checks["lifted"]) is (lift > 0.05)


def test_grasp_heldout_predicate_reads_the_red_box_only():
    b = StateBuilder(get_task(GSC))
    for name in DISTRACTORS:
        b.move(name, [0.0, 0.0, 0.20])  # every distractor lifted high: not a success
    b.grip("right", False)
    assert not bool(b.evaluate().success)
    b.move("cube", [0.0, 0.0, 0.06])
    assert bool(b.evaluate().success)


def test_grasp_heldout_expert_quick():
    _expert_quick(GSC, [1000, 1001])
