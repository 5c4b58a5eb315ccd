"""The camera an episode looks through: its pose, the paper's camera actions, the passive bundle.

Spec (FACTS.md "Semantic camera views", paper appendix "Bounded active camera action space"):

- Every episode starts in the head view "center_high": the camera at (0, -0.58, 1.48) looks at
  (0.17 * side, GC_y - 0.02, max(0.86, GC_z - 0.05)), vertical FOV 37 deg; side = +1 for the
  right arm (every single-arm task), 0 for dual-arm tasks, whose GC is the midpoint of the two.
- A semantic view puts the camera at c + offset and aims it at c, where c is the selected arm's
  finger midpoint (GC), or the midpoint of both GCs; the offset's x is mirrored for the left arm
  and unmirrored for `both`. In single-arm tasks the five views target the active arm; in
  dual-arm tasks the generic views target the midpoint and `view_left_*`, `view_right_*`,
  `view_both_*` select the target. The position is clamped to the camera workspace
  x [-0.85, 0.85], y [-0.95, 0.35], z [0.78, 1.85] first, then aimed, so a clamped view still
  looks at c. Observer views have a vertical FOV of 55 deg.
- Increments act in the current camera frame: `move_left/right/up/down` translate 5 cm along
  the camera's left/right/up/down; `zoom_in/out` translate 8 cm along the view axis;
  `yaw_left/right` rotate 10 deg about world z; `pitch_up/down` rotate 10 deg about the
  camera-left axis. The result is clamped to the workspace (orientation kept).

Where the paper is silent, the reference harness's behaviour holds (spec PROTOCOL_FACTS.md
4.4; docs/PROTOCOL.md):
- A rotation turns the camera in place, about its own position: yaw about world +z, pitch
  about the camera-left axis; the point it looks at moves. `yaw_left` is +10 deg about world +z
  (the view turns left, counter-clockwise seen from above). `pitch_up` is +10 deg right-hand
  about camera-left, which tilts the view direction down (the reference's sign); `pitch_down`
  tilts it up.
- Zooming moves the camera, not the lens (the FOV is fixed); the focus distance shrinks with
  `zoom_in` down to 5 cm, never through the focus point.
- The camera never follows the gripper: a view is centred on GC at the moment it is taken.
  The view's name is recorded (after increments e.g. "topdown (adjusted)") but never shown to
  the model, which knows its view from its own camera actions.

The passive bundle is the five semantic views on the current GC, clamped like the active ones:
the paper's text (a strict subset of the viewpoints reachable in active mode) wins over the
reference harness's fixed world topdown and control-point anchors.

Everything here is a pure function over `CameraPose`; camera actions never touch physics. The
camera's numbers (pose, FOV) are evaluator-side calibration and never reach a prompt.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from vabench.protocol.vocabulary import CAMERA_INCREMENTS, CAMERA_TARGETS, CAMERA_VIEWS

VIEWS = CAMERA_VIEWS
"""The five semantic views, in the fixed order of the passive bundle."""

VIEW_OFFSETS: Mapping[str, tuple[float, float, float]] = {
    "topdown": (0.0, 0.0, 0.68),
    "side": (0.58, -0.02, 0.06),
    "front_side_45": (0.44, -0.44, 0.18),
    "side_top_45": (0.48, -0.02, 0.48),
    "oblique_45": (0.42, -0.42, 0.42),
}
VIEW_UP: Mapping[str, tuple[float, float, float]] = {
    "topdown": (0.0, 1.0, 0.0),
    **{v: (0.0, 0.0, 1.0) for v in VIEWS[1:]},
}
TARGETS = CAMERA_TARGETS

HEAD_VIEW = "center_high"
HEAD_POS = (0.0, -0.58, 1.48)
HEAD_FOVY = 37.0
OBSERVER_FOVY = 55.0
NEAR, FAR = 0.05, 100.0

WORKSPACE_LO = np.array([-0.85, -0.95, 0.78])
WORKSPACE_HI = np.array([0.85, 0.35, 1.85])

MOVE_STEP = 0.05  # m
ZOOM_STEP = 0.08  # m
TURN_STEP = math.radians(10.0)
MIN_FOCUS = 0.05  # m: zoom_in never passes through the focus point

INCREMENTS = CAMERA_INCREMENTS
"""The camera moves relative to the current view (the model's names, `vabench.protocol`)."""


@dataclass(frozen=True)
class CameraPose:
    """Where a camera is and how it is turned.

    `rot` has the camera axes as columns in MuJoCo's convention: x = image right, y = image up,
    z = backwards (the camera looks along -z). `focus` is the distance to the point it was aimed
    at; rotations turn about that point.
    """

    pos: np.ndarray
    rot: np.ndarray
    focus: float
    fovy: float
    view: str
    adjusted: bool = False

    @property
    def forward(self) -> np.ndarray:
        return -self.rot[:, 2]

    @property
    def right(self) -> np.ndarray:
        return self.rot[:, 0]

    @property
    def up(self) -> np.ndarray:
        return self.rot[:, 1]

    @property
    def focus_point(self) -> np.ndarray:
        return self.pos + self.focus * self.forward

    @property
    def label(self) -> str:
        """The view name the model sees."""
        return f"{self.view} (adjusted)" if self.adjusted else self.view

    def quat(self) -> np.ndarray:
        """Orientation as a unit quaternion (w, x, y, z), for MuJoCo's `cam_quat`."""
        return mat_to_quat(self.rot)


def clamp_to_workspace(pos: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(pos, float), WORKSPACE_LO, WORKSPACE_HI)


def look_at(pos: np.ndarray, target: np.ndarray, up_hint: Sequence[float]) -> np.ndarray:
    """Camera axes (columns right, up, back) at `pos` looking at `target`, image-up towards
    `up_hint` (ignored when it is parallel to the view axis: then world +y, else +x)."""
    forward = np.asarray(target, float) - np.asarray(pos, float)
    norm = np.linalg.norm(forward)
    if norm < 1e-9:
        raise ValueError("camera position and target coincide")
    forward /= norm
    for hint in (np.asarray(up_hint, float), np.array([0.0, 1.0, 0.0]), np.array([1.0, 0, 0])):
        right = np.cross(forward, hint)
        if np.linalg.norm(right) > 1e-6:
            break
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return np.stack([right, up, -forward], axis=1)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Right-hand rotation matrix of `angle` radians about the unit vector `axis`."""
    x, y, z = np.asarray(axis, float) / np.linalg.norm(axis)
    c, s = math.cos(angle), math.sin(angle)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
    )


def mat_to_quat(rot: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method, w >= 0)."""
    m = np.asarray(rot, float)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    out = np.array(q)
    return out if out[0] >= 0 else -out


def _aimed(pos: np.ndarray, target: np.ndarray, up: Sequence[float], fovy: float, view: str):
    return CameraPose(
        pos=pos,
        rot=look_at(pos, target, up),
        focus=float(np.linalg.norm(target - pos)),
        fovy=fovy,
        view=view,
    )


def target_point(gcs: Mapping[str, np.ndarray], target: str) -> tuple[np.ndarray, float]:
    """The point a view is centred on and the sign of its lateral offset."""
    if target == "both":
        missing = {"left", "right"} - set(gcs)
        if missing:
            raise ValueError(f"'both' views need the GC of both arms; missing {sorted(missing)}")
        return (np.asarray(gcs["left"], float) + np.asarray(gcs["right"], float)) / 2, 1.0
    if target not in gcs:
        raise ValueError(f"no arm {target!r} in this scene; arms: {sorted(gcs)}")
    return np.asarray(gcs[target], float), (-1.0 if target == "left" else 1.0)


def default_target(arms: Sequence[str]) -> str:
    """Whom the generic views and the head camera follow: the only arm, or both."""
    return arms[0] if len(arms) == 1 else "both"


def head_view(gcs: Mapping[str, np.ndarray], arms: Sequence[str]) -> CameraPose:
    """The initial view of every episode (FACTS "Head camera")."""
    target = default_target(arms)
    c, _ = target_point(gcs, target)
    side = {"right": 1.0, "left": -1.0, "both": 0.0}[target]
    look = np.array([0.17 * side, c[1] - 0.02, max(0.86, c[2] - 0.05)])
    return _aimed(np.array(HEAD_POS, float), look, (0.0, 0.0, 1.0), HEAD_FOVY, HEAD_VIEW)


def semantic_view(view: str, gcs: Mapping[str, np.ndarray], target: str) -> CameraPose:
    """The camera of semantic view `view` centred on `target` ("left", "right" or "both")."""
    if view not in VIEW_OFFSETS:
        raise ValueError(f"unknown view {view!r}; views: {list(VIEWS)}")
    c, sign = target_point(gcs, target)
    ox, oy, oz = VIEW_OFFSETS[view]
    pos = clamp_to_workspace(c + np.array([sign * ox, oy, oz]))
    name = view if target in ("right", "left") and len(gcs) == 1 else f"{target}_{view}"
    return _aimed(pos, c, VIEW_UP[view], OBSERVER_FOVY, name)


def passive_bundle(gcs: Mapping[str, np.ndarray], arms: Sequence[str]) -> list[CameraPose]:
    """The five views of the passive protocol, in their fixed order, on the current GC."""
    target = default_target(arms)
    return [semantic_view(v, gcs, target) for v in VIEWS]


def camera_actions(arms: Sequence[str]) -> list[str]:
    """Every camera action name (without the "camera." prefix) valid in a scene with `arms`."""
    names = [f"view_{v}" for v in VIEWS]
    if len(arms) > 1:
        names += [f"view_{t}_{v}" for t in TARGETS for v in VIEWS]
    return names + list(INCREMENTS)


def parse_view_action(name: str, arms: Sequence[str]) -> tuple[str, str] | None:
    """(view, target) for a semantic-view action name, None for an increment."""
    if not name.startswith("view_"):
        return None
    rest = name[len("view_") :]
    if rest in VIEW_OFFSETS:
        return rest, default_target(arms)
    target, _, view = rest.partition("_")
    if len(arms) > 1 and target in TARGETS and view in VIEW_OFFSETS:
        return view, target
    raise ValueError(f"unknown camera action {name!r}; valid: {camera_actions(arms)}")


def apply_camera_action(
    camera: CameraPose, name: str, gcs: Mapping[str, np.ndarray], arms: Sequence[str]
) -> CameraPose:
    """The camera after action `name` (e.g. "view_topdown", "yaw_left"; no "camera." prefix)."""
    name = name.removeprefix("camera.")
    view = parse_view_action(name, arms)
    if view is not None:
        return semantic_view(view[0], gcs, view[1])
    if name not in INCREMENTS:
        raise ValueError(f"unknown camera action {name!r}; valid: {camera_actions(arms)}")
    return increment(camera, name)


def increment(camera: CameraPose, name: str) -> CameraPose:
    """One fixed-step move, zoom or turn in the current camera frame (see module docstring)."""
    pos, rot, focus = camera.pos, camera.rot, camera.focus
    kind, _, direction = name.partition("_")
    if kind == "move":
        axis = {"left": -camera.right, "right": camera.right, "up": camera.up, "down": -camera.up}
        pos = pos + MOVE_STEP * axis[direction]
    elif kind == "zoom":
        sign = 1.0 if direction == "in" else -1.0
        pos = pos + sign * ZOOM_STEP * camera.forward
        focus = max(MIN_FOCUS, focus - sign * ZOOM_STEP)
    else:  # a turn in place: the position stays, the view direction turns
        if kind == "yaw":  # +z turns the view direction to the left (counter-clockwise)
            angle = TURN_STEP if direction == "left" else -TURN_STEP
            turn = rotation_about(np.array([0.0, 0.0, 1.0]), angle)
        else:  # a positive turn about camera-left (pitch_up) tilts the view direction down
            angle = TURN_STEP if direction == "up" else -TURN_STEP
            turn = rotation_about(-camera.right, angle)
        rot = turn @ rot
    return CameraPose(
        pos=clamp_to_workspace(pos),
        rot=rot,
        focus=focus,
        fovy=camera.fovy,
        view=camera.view,
        adjusted=True,
    )
