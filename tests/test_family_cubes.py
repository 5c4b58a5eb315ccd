"""grasp_single_cube and place_single_cube: ranges of 200 consecutive seeds and the predicate
on constructed states at each threshold. Numbers transcribed from the paper's tables
(tab:seed-spec-grasp, tab:seed-spec-place) and FACTS, independently of the modules."""

from __future__ import annotations

import numpy as np
import pytest

from tests.task_states import StateBuilder
from vabench.tasks import get_task

TABLE_Z = 0.741
SEEDS = range(1000, 1200)
EPS = 1e-9
CUBE_HALF = 0.025  # FACTS: 0.05 cube
PAD_HALF_THICK = 0.003  # FACTS: pad 3 mm half-thick, half-size 0.06


def _yaw_deg(quat) -> float:
    w, x, y, z = quat
    assert abs(x) < 1e-12 and abs(y) < 1e-12  # resting flat: a pure yaw
    return float(np.degrees(2 * np.arctan2(z, w)))


def _inside(v, lo, hi) -> bool:
    return lo - EPS <= v <= hi + EPS


@pytest.mark.parametrize("name", ["grasp_single_cube", "place_single_cube"])
def test_cube_samples_in_range(name):
    task = get_task(name)
    for seed in SEEDS:
        pos, quat = task.sample(seed).poses["cube"]
        assert _inside(pos[0], 0.18, 0.26) and _inside(pos[1], -0.16, -0.06), seed
        assert pos[2] == pytest.approx(TABLE_Z + CUBE_HALF)
        assert _inside(_yaw_deg(quat), -45.0, 45.0), seed


def test_pad_samples_in_range_and_cube_pose_matches_the_grasp_task():
    place, grasp = get_task("place_single_cube"), get_task("grasp_single_cube")
    for seed in SEEDS:
        sample = place.sample(seed)
        pos, quat = sample.poses["pad"]
        assert _inside(pos[0], 0.10, 0.14) and _inside(pos[1], 0.0, 0.04), seed
        assert pos[2] == pytest.approx(TABLE_Z + PAD_HALF_THICK)
        assert _yaw_deg(quat) == 0.0
    # "Cube as in grasp_single_cube": the same distribution, drawn first from the same seed
    np.testing.assert_array_equal(
        place.sample(1234).poses["cube"][0], grasp.sample(1234).poses["cube"][0]
    )


# -- grasp_single_cube: lifted > 50 mm and the right gripper closed -------------------------
@pytest.mark.parametrize(
    ("lift", "closed", "ok"),
    [(0.0505, True, True), (0.0495, True, False), (0.0505, False, False), (0.20, True, True)],
)
def test_grasp_cube_predicate(lift, closed, ok):
    b = StateBuilder(get_task("grasp_single_cube"))
    b.move("cube", [0.0, 0.0, lift]).grip("right", not closed)
    ev = b.evaluate()
    assert bool(ev.success) is ok
    assert bool(ev.checks["lifted"]) is (lift > 0.05)


# -- place_single_cube ------------------------------------------------------------------------
def _placed(**edits) -> StateBuilder:
    """The cube resting on the pad centre, released, touching, lift latched; then `edits`."""
    b = StateBuilder(get_task("place_single_cube"))
    pad = b.pos("pad").copy()
    b.set_pos("cube", pad + [0.0, 0.0, PAD_HALF_THICK + CUBE_HALF])
    b.touch("cube", "pad").latch("was_lifted").grip("right", True)
    for key, value in edits.items():
        if key == "dx":
            b.move("cube", [value, 0.0, 0.0])
        elif key == "dy":
            b.move("cube", [0.0, value, 0.0])
        elif key == "dz":
            b.move("cube", [0.0, 0.0, value])
        elif key == "pad_shift":
            b.move("pad", [value, 0.0, 0.0])
            b.move("cube", [value, 0.0, 0.0])  # the cube stays centred on the moved pad
        elif key == "touch":
            b.touch("cube", "pad", value)
        elif key == "latched":
            b.latch("was_lifted", value)
        elif key == "open":
            b.grip("right", value)
    return b


@pytest.mark.parametrize(
    ("edits", "ok", "check"),
    [
        ({}, True, None),
        ({"dx": 0.0345}, True, "xy_within_tolerance"),
        ({"dx": -0.0355}, False, "xy_within_tolerance"),
        ({"dy": 0.0345}, True, "xy_within_tolerance"),
        ({"dy": 0.0355}, False, "xy_within_tolerance"),
        ({"dz": 0.0345}, True, "height_within_tolerance"),
        ({"dz": 0.0355}, False, "height_within_tolerance"),
        ({"pad_shift": 0.0019}, True, "target_not_displaced"),
        ({"pad_shift": 0.0021}, False, "target_not_displaced"),
        ({"touch": False}, False, "contact"),
        ({"open": False}, False, "gripper_open"),
        ({"latched": False}, False, "was_lifted"),
    ],
)
def test_place_cube_predicate_thresholds(edits, ok, check):
    ev = _placed(**edits).evaluate()
    assert bool(ev.success) is ok, ev.checks
    if check:
        assert bool(ev.checks[check]) is ok


def test_place_cube_lift_latch_sets_from_the_state_and_persists():
    b = StateBuilder(get_task("place_single_cube"))
    b.move("cube", [0.0, 0.0, 0.0505])
    ev = b.evaluate()
    assert bool(ev.latched[0]) and not bool(ev.success)
    b.move("cube", [0.0, 0.0, -0.0505])  # back down: the latch stays once set
    b.latched = np.asarray(ev.latched)
    assert bool(b.evaluate().latched[0])
    b2 = StateBuilder(get_task("place_single_cube"))
    b2.move("cube", [0.0, 0.0, 0.0495])
    assert not bool(b2.evaluate().latched[0])
