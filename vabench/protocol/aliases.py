"""The spellings of a decision that the benchmark's reference harness accepts, rewritten into
vabench's one form before dispatch (PROTOCOL_FACTS 3.3). Pure functions of the decoded object.

- Null fields are absent: `"tool": null` beside an action is not a tool call, `"arm": null`
  is no arm (also inside the sides of a dual move).
- `tool_name` / `tool_args` stand for `tool` / `args`; `args: null` is `{}`.
- Tool aliases: `history.image` and `image.history` are `camera.history`, `robot.geometry` is
  `geometry.verify`.
- An `action` that names a tool is that tool call; its arguments are `args` (or `tool_args`),
  else the other fields of the object (what a model writes as `{"action": "camera.history",
  "step": 3}`).
- Axes: any case and surrounding space; in a local rotation `x`, `y`, `z` mean `rx`, `ry`,
  `rz`; in a world rotation `rx`, `ry`, `rz` mean `x`, `y`, `z` (its axes are the world's,
  named as in `gripper.move_world`; the reference's compact name spells them `rx|ry|rz`).
- Signs: `+`, `pos`, `positive`, `ccw`, `+1`, `1` and `-`, `neg`, `negative`, `cw`, `-1`, in
  any case, also as the numbers 1 and -1; for moves and rotations alike.
- Legacy compact action names: `[<arm>_]gripper.world_<x|y|z>_<pos|neg>.<N>mm` is a
  `gripper.move_world`, `[<arm>_]gripper.local_rotate_<rx|ry|rz>_<ccw|cw>.<N>deg` a
  `gripper.rotate_local`, `[<arm>_]gripper.rotate_<rx|ry|rz>_<ccw|cw>.<N>deg` a
  `gripper.rotate_world` (the reference's world rotation: a turn about the fixed world axis,
  GC held, accepted but not advertised; vabench executes it, `robot.RotateWorld`).
- `"stop": true` (the boolean only) stops; any other `stop` value is ignored, as in the
  reference (`{"action": ..., "stop": false}` is that action).
"""

from __future__ import annotations

import re
from typing import Any

from vabench.protocol.vocabulary import TOOL_NAMES

SIGN_ALIASES = {
    "+": "+",
    "pos": "+",
    "positive": "+",
    "ccw": "+",
    "+1": "+",
    "1": "+",
    "-": "-",
    "neg": "-",
    "negative": "-",
    "cw": "-",
    "-1": "-",
}
"""Every spelling of a sign and the sign it means (matched after strip and lower-case)."""
TOOL_ALIASES = {
    "history.image": "camera.history",
    "image.history": "camera.history",
    "robot.geometry": "geometry.verify",
}
ROTATE_LOCAL = "gripper.rotate_local"
ROTATE_WORLD = "gripper.rotate_world"
_MOVE = re.compile(r"^(?:(left|right)_)?gripper\.world_([xyz])_(pos|neg)\.(\d+(?:\.\d+)?)mm$")
_LOCAL = re.compile(
    r"^(?:(left|right)_)?gripper\.local_rotate_(rx|ry|rz)_(ccw|cw)\.(\d+(?:\.\d+)?)deg$"
)
_WORLD = re.compile(r"^(?:(left|right)_)?gripper\.rotate_(rx|ry|rz)_(ccw|cw)\.(\d+(?:\.\d+)?)deg$")
_AXIS_ACTIONS = ("gripper.move_world", ROTATE_LOCAL, ROTATE_WORLD)


def sign(value: Any) -> Any:
    """The sign a spelling means ("+" or "-"); anything else unchanged (and refused later)."""
    if isinstance(value, bool):
        return value  # a boolean is no sign
    if isinstance(value, int | float) and value in (1, -1):
        return "+" if value > 0 else "-"
    if isinstance(value, str):
        return SIGN_ALIASES.get(value.strip().lower(), value)
    return value


def axis(value: Any, action: str | None = None) -> Any:
    """An axis in lower case; `x|y|z` of a local rotation as `rx|ry|rz`, `rx|ry|rz` of a
    world rotation as `x|y|z` (`action`: the action the axis belongs to)."""
    if not isinstance(value, str):
        return value
    name = value.strip().lower()
    if action == ROTATE_LOCAL and name in ("x", "y", "z"):
        return "r" + name
    if action == ROTATE_WORLD and name in ("rx", "ry", "rz"):
        return name[1:]
    return name


def _number(text: str) -> float | int:
    value = float(text)
    return int(value) if value.is_integer() else value


def _legacy(name: str) -> dict[str, Any] | None:
    """The parameterized form of a legacy compact action name, None if it is not one."""
    if m := _MOVE.match(name):
        arm, ax, sg, n = m.groups()
        fields = {"action": "gripper.move_world", "axis": ax, "sign": "+" if sg == "pos" else "-"}
        fields["distance_mm"] = _number(n)
    elif (m := _LOCAL.match(name)) or (m := _WORLD.match(name)):
        arm, ax, sg, n = m.groups()
        action = ROTATE_LOCAL if name.split(".")[1].startswith("local") else ROTATE_WORLD
        fields = {"action": action, "axis": axis(ax, action), "sign": sign(sg)}
        fields["angle_deg"] = _number(n)
    else:
        return None
    if arm is not None:
        fields["arm"] = arm
    return fields


def _side(value: Any) -> Any:
    if not isinstance(value, dict):
        return value
    side = {k: v for k, v in value.items() if v is not None}
    if "axis" in side:
        side["axis"] = axis(side["axis"])
    if "sign" in side:
        side["sign"] = sign(side["sign"])
    return side


def normalise(obj: dict[str, Any]) -> dict[str, Any]:
    """The decision `obj` in vabench's one form (module docstring); a new dict."""
    out = {k: v for k, v in obj.items() if v is not None}
    if out.get("stop") is not True:
        out.pop("stop", None)
    if "tool" not in out and "tool_name" in out:
        out["tool"] = out["tool_name"]
    if "args" not in out and "tool_args" in out:
        out["args"] = out["tool_args"]
    out.pop("tool_name", None)
    out.pop("tool_args", None)
    if isinstance(out.get("tool"), str):
        out["tool"] = TOOL_ALIASES.get(out["tool"], out["tool"])
    name = out.get("action")
    if not isinstance(name, str):
        return out
    if "tool" not in out and (name in TOOL_NAMES or name in TOOL_ALIASES):
        if "args" not in out:
            out["args"] = {k: v for k, v in out.items() if k not in ("action", "reason")}
        rest = {k: v for k, v in out.items() if k in ("args", "reason", "stop")}
        return {"tool": TOOL_ALIASES.get(name, name), **rest}
    if (legacy := _legacy(name)) is not None:
        out = {**{k: v for k, v in out.items() if k not in legacy}, **legacy}
        name = legacy["action"]
    if name in _AXIS_ACTIONS and "axis" in out:
        out["axis"] = axis(out["axis"], name)
    if "sign" in out:
        out["sign"] = sign(out["sign"])
    for side in ("left", "right"):
        if side in out:
            out[side] = _side(out[side])
    return out
