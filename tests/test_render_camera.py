"""Camera geometry: the paper's semantic views, increments and clamps (FACTS "Semantic camera
views"; the offsets are transcribed here independently of vabench.render.camera)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vabench.render import camera as cam

OFFSETS = {  # FACTS table, right arm
    "topdown": (0.0, 0.0, 0.68),
    "side": (0.58, -0.02, 0.06),
    "front_side_45": (0.44, -0.44, 0.18),
    "side_top_45": (0.48, -0.02, 0.48),
    "oblique_45": (0.42, -0.42, 0.42),
}
LO, HI = np.array([-0.85, -0.95, 0.78]), np.array([0.85, 0.35, 1.85])
SINGLE = ("right",)
DUAL = ("left", "right")
GC_R = np.array([0.20, -0.10, 0.90])
GC_L = np.array([-0.25, 0.05, 0.95])


def aims_at(pose: cam.CameraPose, point: np.ndarray) -> bool:
    d = point - pose.pos
    return bool(np.allclose(pose.forward, d / np.linalg.norm(d), atol=1e-9))


def is_rotation(r: np.ndarray) -> bool:
    return bool(np.allclose(r.T @ r, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(r), 1))


@pytest.mark.parametrize("view", list(OFFSETS))
def test_single_arm_views_sit_at_gc_plus_offset_and_look_at_gc(view):
    pose = cam.apply_camera_action(
        cam.head_view({"right": GC_R}, SINGLE), f"view_{view}", {"right": GC_R}, SINGLE
    )
    expected = np.clip(GC_R + np.array(OFFSETS[view]), LO, HI)
    np.testing.assert_allclose(pose.pos, expected, atol=1e-12)
    assert aims_at(pose, GC_R)
    assert is_rotation(pose.rot)
    assert pose.fovy == 55.0
    assert pose.label == view
    if view == "topdown":  # up hint +y: the far side of the table is at the image top
        assert pose.up[1] > 0.99
    else:  # up hint +z: the image is upright
        assert pose.up[2] > 0
        assert abs(pose.right[2]) < 1e-9


@pytest.mark.parametrize("view", list(OFFSETS))
def test_dual_arm_views_mirror_for_left_and_use_the_midpoint_for_both(view):
    gcs = {"left": GC_L, "right": GC_R}
    ox, oy, oz = OFFSETS[view]
    head = cam.head_view(gcs, DUAL)
    left = cam.apply_camera_action(head, f"camera.view_left_{view}", gcs, DUAL)
    np.testing.assert_allclose(left.pos, np.clip(GC_L + [-ox, oy, oz], LO, HI), atol=1e-12)
    assert aims_at(left, GC_L)
    assert left.label == f"left_{view}"
    right = cam.apply_camera_action(head, f"view_right_{view}", gcs, DUAL)
    np.testing.assert_allclose(right.pos, np.clip(GC_R + [ox, oy, oz], LO, HI), atol=1e-12)
    mid = (GC_L + GC_R) / 2
    both = cam.apply_camera_action(head, f"view_both_{view}", gcs, DUAL)
    np.testing.assert_allclose(both.pos, np.clip(mid + [ox, oy, oz], LO, HI), atol=1e-12)
    assert aims_at(both, mid)
    generic = cam.apply_camera_action(head, f"view_{view}", gcs, DUAL)  # generic = both
    np.testing.assert_allclose(generic.pos, both.pos)


def test_views_are_clamped_to_the_workspace_and_still_aim_at_gc():
    far_gc = np.array([0.5, 0.30, 1.30])  # side view would be at x 1.08, topdown at z 1.98
    for view in OFFSETS:
        pose = cam.semantic_view(view, {"right": far_gc}, "right")
        assert np.all(pose.pos >= LO - 1e-12) and np.all(pose.pos <= HI + 1e-12)
        assert aims_at(pose, far_gc)
    assert cam.semantic_view("side", {"right": far_gc}, "right").pos[0] == pytest.approx(0.85)
    assert cam.semantic_view("topdown", {"right": far_gc}, "right").pos[2] == pytest.approx(1.85)


def test_head_view_follows_facts():
    pose = cam.head_view({"right": GC_R}, SINGLE)
    np.testing.assert_allclose(pose.pos, [0.0, -0.58, 1.48])
    assert aims_at(pose, np.array([0.17, GC_R[1] - 0.02, max(0.86, GC_R[2] - 0.05)]))
    assert pose.fovy == 37.0 and pose.label == "center_high"
    low = np.array([0.2, 0.0, 0.80])  # GC_z - 0.05 below 0.86: look at z 0.86
    assert aims_at(cam.head_view({"right": low}, SINGLE), np.array([0.17, -0.02, 0.86]))
    gcs = {"left": GC_L, "right": GC_R}
    mid = (GC_L + GC_R) / 2
    assert aims_at(cam.head_view(gcs, DUAL), np.array([0.0, mid[1] - 0.02, mid[2] - 0.05]))


@pytest.fixture
def oblique():
    return cam.semantic_view("oblique_45", {"right": GC_R}, "right")


@pytest.mark.parametrize(
    "action, axis, sign",
    [
        ("move_left", "right", -1),
        ("move_right", "right", 1),
        ("move_up", "up", 1),
        ("move_down", "up", -1),
    ],
)
def test_moves_translate_exactly_5cm_in_the_camera_frame(oblique, action, axis, sign):
    after = cam.increment(oblique, action)
    np.testing.assert_allclose(
        after.pos - oblique.pos, sign * 0.05 * getattr(oblique, axis), atol=1e-12
    )
    np.testing.assert_allclose(after.rot, oblique.rot)
    assert after.label == "oblique_45 (adjusted)"


@pytest.mark.parametrize("action, sign", [("zoom_in", 1), ("zoom_out", -1)])
def test_zoom_translates_exactly_8cm_along_the_view_axis(oblique, action, sign):
    after = cam.increment(oblique, action)
    np.testing.assert_allclose(after.pos - oblique.pos, sign * 0.08 * oblique.forward, atol=1e-12)
    np.testing.assert_allclose(after.focus_point, oblique.focus_point, atol=1e-12)


def angle_between(a, b):
    return math.degrees(math.acos(np.clip(np.dot(a, b), -1, 1)))


@pytest.mark.parametrize("action", ["yaw_left", "yaw_right"])
def test_yaw_turns_exactly_10deg_about_world_z(oblique, action):
    after = cam.increment(oblique, action)
    sign = 1 if action == "yaw_left" else -1
    c, s = math.cos(math.radians(10 * sign)), math.sin(math.radians(10 * sign))
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(after.rot, rz @ oblique.rot, atol=1e-12)
    # yaw_left turns the view direction to the left (counter-clockwise seen from above)
    a, b = oblique.forward, after.forward
    turn = a[0] * b[1] - a[1] * b[0]
    assert np.sign(turn) == sign
    np.testing.assert_allclose(after.pos, oblique.pos, atol=1e-12)  # turns in place
    assert is_rotation(after.rot)


@pytest.mark.parametrize("action", ["pitch_up", "pitch_down"])
def test_pitch_turns_exactly_10deg_about_camera_left(oblique, action):
    after = cam.increment(oblique, action)
    assert angle_between(after.forward, oblique.forward) == pytest.approx(10.0, abs=1e-9)
    np.testing.assert_allclose(after.right, oblique.right, atol=1e-12)  # axis unchanged
    # pitch_up is the positive right-hand turn about camera-left: the view tilts down
    lower = after.forward[2] < oblique.forward[2]
    assert lower == (action == "pitch_up")
    np.testing.assert_allclose(after.pos, oblique.pos, atol=1e-12)  # turns in place


def test_increments_clamp_position_to_the_workspace():
    pose = cam.semantic_view("topdown", {"right": np.array([0.4, 0.2, 1.2])}, "right")
    for _ in range(10):
        pose = cam.increment(pose, "zoom_out")  # straight up: z would pass 1.85
    assert pose.pos[2] == pytest.approx(1.85)
    for _ in range(40):
        pose = cam.increment(pose, "move_right")
    assert np.all(pose.pos <= HI + 1e-12) and np.all(pose.pos >= LO - 1e-12)


def test_zoom_in_never_passes_the_focus_point(oblique):
    pose = oblique
    for _ in range(20):
        pose = cam.increment(pose, "zoom_in")
    assert pose.focus == pytest.approx(cam.MIN_FOCUS)
    assert is_rotation(pose.rot)


def test_passive_bundle_is_the_five_views_in_fixed_order():
    gcs = {"right": GC_R}
    bundle = cam.passive_bundle(gcs, SINGLE)
    assert [p.label for p in bundle] == [
        "topdown",
        "side",
        "front_side_45",
        "side_top_45",
        "oblique_45",
    ]
    for pose, view in zip(bundle, OFFSETS, strict=True):
        np.testing.assert_allclose(pose.pos, np.clip(GC_R + OFFSETS[view], LO, HI))


def test_action_names_and_errors():
    single, dual = cam.camera_actions(SINGLE), cam.camera_actions(DUAL)
    assert len(single) == 5 + 10 and len(dual) == 5 + 15 + 10
    assert "view_left_topdown" in dual and "view_left_topdown" not in single
    gcs = {"right": GC_R}
    head = cam.head_view(gcs, SINGLE)
    with pytest.raises(ValueError, match="unknown camera action"):
        cam.apply_camera_action(head, "view_left_topdown", gcs, SINGLE)
    with pytest.raises(ValueError, match="unknown camera action"):
        cam.apply_camera_action(head, "spin", gcs, SINGLE)


def quat_to_rot(q):
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.mark.parametrize("view", list(OFFSETS))
def test_quaternion_matches_rotation(view):
    pose = cam.semantic_view(view, {"right": GC_R}, "right")
    for p in (pose, cam.increment(pose, "yaw_left"), cam.increment(pose, "pitch_down")):
        np.testing.assert_allclose(quat_to_rot(p.quat()), p.rot, atol=1e-12)
