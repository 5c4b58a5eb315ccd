"""The episode's inspection tools (spec FACTS.md, "Tools"): they never advance the simulator,
and their results return to the same thread as JSON text, with images where a tool shows one.

- `geometry.verify`: the robot's own geometry, which the model may know: gripper aperture and
  finger dimensions, where GC and the control point lie, the axis definitions, the
  end-effector bounds and the arm bases. Nothing about objects or cameras.
- `camera.history {"step": k}`: the model image of an earlier step, re-attached.

The engine calls `geometry_result(arms)` / `camera_history(frames, step)` and appends the
`ToolResult` with `Conversation.add_tool_result(result.text, result.images, step=result.step)`.
The demonstration tools (`expert.*`) live with the demonstration code.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from vabench.llm_pool.messages import Image


@dataclass(frozen=True)
class ToolResult:
    """A tool's answer for the thread: JSON text, and the images it shows (if any)."""

    tool: str
    text: str
    images: tuple[Image, ...] = ()
    step: int | None = None
    """The step the images belong to (their placeholder names it once they age out)."""
    ok: bool = True


def tool_text(tool: str, payload: Mapping[str, Any]) -> str:
    """The JSON line a tool result is sent as: {"tool": name, ...payload}."""
    return json.dumps({"tool": tool, **payload})


def _mm(metres: float) -> float:
    return round(metres * 1000.0, 1)


def geometry_verify(arms: Sequence[str]) -> dict[str, Any]:
    """The robot self-geometry of a task with `arms`, from `sim_mjx.robot_constants` (the
    MJCF's single source of truth for the gripper boxes). Lengths in mm unless the key says m."""
    # Imported here: the constants live in a package that loads JAX, which the rest of the
    # agent package does not need.
    from vabench.sim_mjx import robot_constants as rc

    unknown = [a for a in arms if a not in rc.ARMS]
    if not arms or unknown:
        raise ValueError(f"arms: expected a subset of {rc.ARMS}, got {tuple(arms)}")
    (finger_x, _, _), (finger_hx, finger_hy, finger_hz) = rc.FINGER_A_BOX
    _, (palm_hx, palm_hy, palm_hz) = rc.PALM_BOX
    return {
        "frame": {
            "x": "to the robot's right",
            "y": "away from the robot, towards the far side of the table",
            "z": "up",
            "positions": "metres, world frame",
        },
        "gripper": {
            "max_aperture_mm": _mm(2 * rc.FINGER_OPEN),
            "finger_length_mm": _mm(2 * finger_hx),
            "finger_thickness_mm": _mm(2 * finger_hy),
            "finger_width_mm": _mm(2 * finger_hz),
            "fingertip_beyond_gc_mm": _mm(finger_x + finger_hx - rc.PAD_X),
            "gc_ahead_of_control_point_mm": _mm(rc.PAD_X - rc.EE_SITE_X),
            "palm_width_mm": _mm(2 * palm_hy),
            "palm_thickness_mm": _mm(2 * palm_hz),
            "palm_depth_mm": _mm(2 * palm_hx),
            "gc": (
                "finger_center_xyz: the midpoint between the two finger pads, "
                f"{_mm(finger_x + finger_hx - rc.PAD_X):g} mm behind the fingertips"
            ),
            "control_point": (
                "control_eepose_xyz: the centre of the palm face, "
                f"{_mm(rc.PAD_X - rc.EE_SITE_X):g} mm behind GC along rx"
            ),
            "axes": {
                "rx": "approach axis: from the palm towards the fingertips",
                "ry": "finger-closing axis: the fingers move along it, symmetric about GC",
                "rz": "palm-side axis: perpendicular to rx and ry (right-handed)",
            },
            "rotation_rule": "+ is a right-hand rotation about the current local axis; GC fixed",
            "outer_width_open_mm": _mm(2 * rc.FINGER_OPEN + 2 * (2 * finger_hy)),
        },
        "end_effector_bounds_m": {
            axis: [lo, hi]
            for axis, lo, hi in zip("xyz", rc.EE_BOUNDS_LO, rc.EE_BOUNDS_HI, strict=True)
        },
        "arm_base_xyz_m": {arm: list(rc.ARM_BASE_POS[arm]) for arm in arms},
        "motion": {
            "translation_mm": list(rc.MOVE_MM_RANGE),
            "rotation_deg": list(rc.ROTATE_DEG_RANGE),
            "rotation_substep_deg": rc.ROTATE_STEP_DEG,
            "planner": "straight-line moves; avoids only the table; an unreachable target "
            "leaves the arm where it was",
        },
    }


def geometry_result(arms: Sequence[str]) -> ToolResult:
    """`geometry.verify` as a tool result."""
    return ToolResult("geometry.verify", tool_text("geometry.verify", geometry_verify(arms)))


def _ranges(steps: Sequence[int]) -> str:
    """1, 2, 3, 5, 7, 8 -> "1-3, 5, 7-8"."""
    out: list[str] = []
    steps = sorted(steps)
    i = 0
    while i < len(steps):
        j = i
        while j + 1 < len(steps) and steps[j + 1] == steps[j] + 1:
            j += 1
        out.append(str(steps[i]) if i == j else f"{steps[i]}-{steps[j]}")
        i = j + 1
    return ", ".join(out) or "none yet"


def camera_history(frames: Mapping[int, Image], step: Any) -> ToolResult:
    """`camera.history {"step": step}`: the image the model received at `step` (`frames`
    maps step -> that image), or an error naming the valid steps."""
    name = "camera.history"
    if isinstance(step, bool) or not isinstance(step, int):
        error = f"args.step: expected an integer step, got {json.dumps(step, default=str)}"
    elif step not in frames:
        error = f"args.step: no image for step {step}; valid steps: {_ranges(list(frames))}"
    else:
        text = tool_text(name, {"step": step, "result": f"the image of step {step} follows"})
        return ToolResult(name, text, (frames[step],), step=step)
    return ToolResult(name, tool_text(name, {"error": error}), ok=False)
