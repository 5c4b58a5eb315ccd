"""The demonstration summary: the checks of `expert.learn`'s fields and the text every
evaluation observation carries (spec PROTOCOL_FACTS.md 6.4 and 2.5; paper, appendix
"Demonstration-conditioned evaluation protocol").

A model that has inspected the demonstration writes one summary per task: the fields are the
arguments of `expert.learn` themselves, `{"tool": "expert.learn", "args": {"grasp_region":
..., ...}}`, as the benchmark's reference harness takes them. `{"summary": {...}}` (an args
object whose only key is "summary") is read as the same call (vabench's earlier shape).
`parse_summary(args, composite=...)` returns the summary as a dict, or raises
`DecisionError` naming every problem at once (the learning session sends that text back as
the tool's error, so one more call can fix them all). `summary_text(summary)` is the text
shown in every observation of the evaluation episodes (`EpisodeSpec.demonstration_summary`):
the summary as indented JSON, non-ASCII kept.

The checks (the reference's, every reason listed rather than the first):

- `REQUIRED_FIELDS`: present and not empty (null, a blank string, an empty list or object
  are empty); `pre_close_checks` is a non-empty list of non-empty strings.
- `CHECKED_FIELDS`, when present and not null: `task_stage` and `post_grasp_goal` non-empty
  strings, `functional_constraints` a list of non-empty strings, `required_arms` 1 or 2,
  `semantic_ambiguity` a number in [0, 1] (booleans are neither), `affordance_profile` an
  object holding every field of `AFFORDANCE_ENUMS` (one of its values) and of
  `AFFORDANCE_FLAGS` (a boolean).
- Every other field (`FREE_FIELDS`, which the prompt describes, and any a model adds) is kept
  as written, unchecked. No length limits.
- A composite demonstration (the basket's atomic videos): nothing in the arguments may state
  how many objects of a type a scene holds ("two cubes", "1 pen") or name objects by letter
  ("cube A"): the videos' inventory is not the evaluation episode's.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
from collections.abc import Mapping
from typing import Any

from vabench.protocol import DecisionError
from vabench.protocol.errors import show

ARGS = "args"
"""The `DecisionError.field` prefix of summary problems, as the model wrote the call."""
SUMMARY_KEY = "summary"
"""The only key of the accepted wrapper shape `{"summary": {...}}`."""
MODEL_KEY = "summary_model"
"""Who wrote a summary: the records say so (`LearningResult.model`); never shown."""

REQUIRED_FIELDS: dict[str, str] = {
    "grasp_object_part": "which object, and which part of it, the gripper takes",
    "grasp_region": "where on that part the fingers close, and which regions were avoided",
    "grasp_height_or_depth": "how high on the object, or how deep into it, the fingers go",
    "finger_placement": "where each finger sits and along which direction the fingers close",
    "approach_strategy": "how the gripper comes in: direction, order of moves, clearances",
    "posture_or_rotation": "the gripper's orientation before closing, and any rotation needed",
    "pre_close_checks": "a list of what to confirm in the images before closing the gripper",
    "test_lift_rule": (
        "the lift straight after closing that completes the task (the name is historical: "
        "not a short trial lift): how far, and what shows that it worked"
    ),
}
"""Required fields and what each holds (the learning prompt lists them)."""
CHECKED_FIELDS: dict[str, str] = {
    "task_stage": "a string: which stage of the task the grasp serves (initial, handover, tool)",
    "post_grasp_goal": "a string: what happens after the grasp",
    "functional_constraints": (
        "a list of strings: what the object's function demands (upright, opening up, ...)"
    ),
    "required_arms": "1 or 2",
    "semantic_ambiguity": "a number from 0 to 1: how easily the target is confused",
    "affordance_profile": "an object holding all of these fields:",
}
"""Optional fields that are checked when given, and their shapes."""
FREE_FIELDS: dict[str, str] = {
    "avoid_roles": "objects or parts not to grasp or touch, and why",
    "arm_assignment": "which arm does what",
    "coordination_sequence": "the phases of the arms, in order",
    "synchronized_actions": "the moves both arms make together",
    "release_or_completion_rule": "when to release, and what state completes the task",
    "safety_notes": "collisions and risks to avoid",
    "object_strategies": "per object type: how it is grasped, carried and released",
}
"""Optional fields kept as written (any JSON value), with what each is for."""
AFFORDANCE_ENUMS: dict[str, tuple[str, ...]] = {
    "part_shape": (
        "unknown",
        "slender_cylinder",
        "broad_cylinder",
        "box",
        "handle",
        "flat",
        "irregular",
    ),
    "symmetry_class": ("unknown", "continuous", "two_fold", "four_fold", "asymmetric"),
    "centering_tolerance": ("unknown", "strict", "moderate", "permissive"),
    "vertical_tolerance": ("unknown", "strict", "moderate", "permissive"),
}
AFFORDANCE_FLAGS = ("avoid_ends", "requires_bilateral_contact", "requires_dual_arm")

# The videos' inventory in a composite task: a count of one to four of an object type, or an
# object named by a letter. The words "five objects" stay allowed: every episode has five.
_TYPE_COUNT = re.compile(
    r"\b(?:one|two|three|four|1|2|3|4)\s+(?:visually\s+distinct\s+)?(?:cubes?|bottles?|pens?)\b",
    re.IGNORECASE,
)
_LETTERED = re.compile(r"\b(?:cube|bottle|pen)\s+[A-D]\b", re.IGNORECASE)


def unwrap(args: Mapping[str, Any]) -> dict[str, Any]:
    """The summary fields of `expert.learn`'s args: the args themselves, or the object under
    "summary" when that is their only key (a JSON string holding an object is decoded)."""
    if set(args) != {SUMMARY_KEY}:
        return dict(args)
    inner = args[SUMMARY_KEY]
    if isinstance(inner, str):
        with contextlib.suppress(json.JSONDecodeError):
            inner = json.loads(inner)
    if not isinstance(inner, dict):
        raise DecisionError(
            f"{ARGS}.{SUMMARY_KEY}",
            "must be a JSON object of the summary fields, got "
            f"{show(args[SUMMARY_KEY])}; better, put the fields directly in args: "
            + ", ".join(REQUIRED_FIELDS),
        )
    return dict(inner)


def _empty(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, str):
        return not value.strip()
    if isinstance(value, list | dict):
        return not value
    return False


def _text(value: Any) -> bool:
    return isinstance(value, str) and bool(value.strip())


def _text_list(name: str, value: Any, *, non_empty: bool) -> list[tuple[str, str]]:
    where = f"{ARGS}.{name}"
    if not isinstance(value, list):
        return [(where, f"must be a list of non-empty strings, got {show(value)}")]
    if non_empty and not value:
        return [(where, "must hold at least one non-empty string")]
    return [
        (f"{where}[{i}]", f"must be a non-empty string, got {show(item)}")
        for i, item in enumerate(value)
        if not _text(item)
    ]


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _profile(value: Any) -> list[tuple[str, str]]:
    where = f"{ARGS}.affordance_profile"
    if not isinstance(value, dict):
        return [(where, f"must be an object, got {show(value)}")]
    problems = []
    for name, allowed in AFFORDANCE_ENUMS.items():
        if name not in value:
            problems.append((f"{where}.{name}", f"required: one of {', '.join(allowed)}"))
        elif value[name] not in allowed:
            got = show(value[name])
            problems.append((f"{where}.{name}", f"must be one of {', '.join(allowed)}, got {got}"))
    for name in AFFORDANCE_FLAGS:
        if name not in value:
            problems.append((f"{where}.{name}", "required: true or false"))
        elif not isinstance(value[name], bool):
            problems.append((f"{where}.{name}", f"must be true or false, got {show(value[name])}"))
    return problems


def summary_problems(fields: Mapping[str, Any], *, composite: bool) -> list[tuple[str, str]]:
    """(field, message) for every problem of the summary `fields` (module docstring), in the
    order of the required fields, then the checked ones, then the composite rule."""
    problems: list[tuple[str, str]] = []
    for name in REQUIRED_FIELDS:
        value = fields.get(name)
        if _empty(value):
            got = "" if name not in fields else f", got {show(value)}"
            problems.append((f"{ARGS}.{name}", f"required, not empty{got}"))
        elif name == "pre_close_checks":
            problems += _text_list(name, value, non_empty=True)
    for name in ("task_stage", "post_grasp_goal"):
        value = fields.get(name)
        if value is not None and not _text(value):
            problems.append((f"{ARGS}.{name}", f"must be a non-empty string, got {show(value)}"))
    if fields.get("functional_constraints") is not None:
        problems += _text_list(
            "functional_constraints", fields["functional_constraints"], non_empty=False
        )
    arms = fields.get("required_arms")
    if arms is not None and (not _number(arms) or arms not in (1, 2)):
        problems.append((f"{ARGS}.required_arms", f"must be 1 or 2, got {show(arms)}"))
    ambiguity = fields.get("semantic_ambiguity")
    if ambiguity is not None and (
        not _number(ambiguity) or not math.isfinite(ambiguity) or not 0 <= ambiguity <= 1
    ):
        problems.append(
            (f"{ARGS}.semantic_ambiguity", f"must be a number from 0 to 1, got {show(ambiguity)}")
        )
    if fields.get("affordance_profile") is not None:
        problems += _profile(fields["affordance_profile"])
    if composite:
        text = json.dumps(dict(fields), ensure_ascii=False)
        found = [m.group(0) for p in (_TYPE_COUNT, _LETTERED) for m in p.finditer(text)]
        if found:
            problems.append(
                (
                    ARGS,
                    "this task's videos show single skills, not an episode's objects: write "
                    "no count of objects of a type and no lettered object names (found "
                    + ", ".join(json.dumps(f) for f in dict.fromkeys(found))
                    + "); speak of the five objects the current episode names and keep the "
                    "skills per object type",
                )
            )
    return problems


def parse_summary(args: Mapping[str, Any], *, composite: bool = False) -> dict[str, Any]:
    """The summary of `expert.learn`'s `args` (every field kept as written, `MODEL_KEY`
    dropped), or `DecisionError` naming every problem (module docstring)."""
    fields = unwrap(args)
    fields.pop(MODEL_KEY, None)
    problems = summary_problems(fields, composite=composite)
    if problems:
        raise DecisionError(*problems[0], others=problems[1:])
    return fields


def summary_text(summary: Mapping[str, Any]) -> str:
    """The summary as every observation shows it: indented JSON, non-ASCII kept, without
    `MODEL_KEY`. Every number in it is one the model wrote."""
    shown = {k: v for k, v in summary.items() if k != MODEL_KEY}
    return json.dumps(shown, indent=2, ensure_ascii=False)
