"""The demonstration summary: its schema, its validation and the text every observation carries
(spec FACTS.md, "Demonstration protocol"; paper, appendix "Demonstration-conditioned evaluation
protocol").

A model that has inspected the demonstration video writes one summary per task through
`expert.learn {"summary": {...}}`. `parse_summary(obj)` turns that object into a
`DemoSummary`, or raises `DecisionError` naming every missing or invalid field at once (the
error text is the repair feedback, so one retry can fix them all). `summary_text(summary)` is
the compact form inserted in every observation of the evaluation episodes
(`EpisodeSpec.demonstration_summary`).

Decisions the spec leaves open, made here:

- Required text fields are non-empty strings (surrounding whitespace stripped);
  `pre_close_checks` is a non-empty list of non-empty strings.
- The optional descriptive fields (`avoid_roles`, `coordination_sequence`,
  `synchronized_actions`, `safety_notes`, ...) take a string or a list of strings: some are
  naturally ordered lists, and forcing one shape costs repairs without adding meaning.
  `arm_assignment` also takes an object {"left": ..., "right": ...}.
- `required_arms` is 1 or 2; `semantic_ambiguity` a number in [0, 1]; booleans are rejected
  for both (JSON true is not 1).
- Unknown fields are rejected, naming the valid ones: the summary is the only text that
  crosses from the learning stage into evaluation, so nothing rides along unchecked.
- Length limits, so that a summary cannot smuggle a long text into every observation:
  `MAX_TEXT_CHARS` per string, `MAX_LIST_ITEMS` per list, and `MAX_SUMMARY_CHARS` for the
  whole `summary_text` (about 1,500 tokens at most, repeated every decision).
- A summary given as a string is accepted only when it decodes to a JSON object (LearnArgs
  admits strings; FACTS defines the summary as structured fields).
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
)
from pydantic_core import ErrorDetails

from vabench.protocol import DecisionError
from vabench.protocol.errors import repair_message, show

MAX_TEXT_CHARS = 500
"""Characters of one string field or list item."""
MAX_LIST_ITEMS = 10
"""Items of one list field."""
MAX_SUMMARY_CHARS = 6000
"""Characters of the whole `summary_text`."""

SUMMARY_FIELD = "args.summary"
"""The `DecisionError.field` prefix of summary problems, as the model wrote the call."""

SUMMARY_HEADER = "learned from the task's demonstration video."
"""The first line of `summary_text` (no digits: every number in the text is the model's)."""


def _no_bool(value: Any) -> Any:
    # pydantic's lax mode reads true as 1; a boolean count or score is a mistake.
    if isinstance(value, bool):
        raise ValueError(f"must be a number, got {json.dumps(value)}")
    return value


def _arm_count(value: Any) -> Any:
    if isinstance(value, bool) or value not in (1, 2):
        raise ValueError(f"must be 1 or 2, got {json.dumps(value, default=str)}")
    return int(value)


Text = Annotated[
    str, StringConstraints(strip_whitespace=True, min_length=1, max_length=MAX_TEXT_CHARS)
]
TextList = Annotated[list[Text], Field(min_length=1, max_length=MAX_LIST_ITEMS)]
TextOrList = Text | TextList
ArmTexts = Annotated[dict[Literal["left", "right"], Text], Field(min_length=1)]


class DemoSummary(BaseModel):
    """One task's demonstration summary (FACTS field list; descriptions feed the prompt)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # -- required -------------------------------------------------------------------------
    grasp_object_part: Text = Field(description="which object, and which part of it, is grasped")
    grasp_region: Text = Field(description="where on that part the fingers close")
    grasp_height_or_depth: Text = Field(
        description="how high on the object, or how deep into it, the fingers go"
    )
    finger_placement: Text = Field(
        description="where each finger sits and along which direction the fingers close"
    )
    approach_strategy: Text = Field(
        description="how the gripper approaches: direction, order of moves, clearances"
    )
    posture_or_rotation: Text = Field(
        description="gripper orientation before closing, and any rotation needed"
    )
    pre_close_checks: TextList = Field(
        description="list of what to verify in the images before closing the gripper"
    )
    test_lift_rule: Text = Field(
        description="how to test the grasp after closing and what counts as secure"
    )
    # -- optional -------------------------------------------------------------------------
    task_stage: TextOrList | None = Field(None, description="the stages of the task, in order")
    post_grasp_goal: Text | None = Field(None, description="what happens after the grasp")
    functional_constraints: TextOrList | None = Field(
        None, description="constraints from the object's function (upright, opening up, ...)"
    )
    required_arms: Annotated[Literal[1, 2], BeforeValidator(_arm_count)] | None = Field(
        None, description="1 or 2"
    )
    semantic_ambiguity: (
        Annotated[float, BeforeValidator(_no_bool), Field(ge=0, le=1, allow_inf_nan=False)] | None
    ) = Field(None, description="0 to 1: how ambiguous the target object is")
    avoid_roles: TextOrList | None = Field(
        None, description="objects or parts to avoid touching or confusing with the target"
    )
    arm_assignment: Text | ArmTexts | None = Field(
        None, description='which arm does what; a string or {"left": ..., "right": ...}'
    )
    coordination_sequence: TextOrList | None = Field(
        None, description="the order in which the arms act"
    )
    synchronized_actions: TextOrList | None = Field(
        None, description="moves both arms must make together"
    )
    release_or_completion_rule: Text | None = Field(
        None, description="when to release, or what state completes the task"
    )
    safety_notes: TextOrList | None = Field(None, description="collisions and risks to avoid")


REQUIRED_FIELDS = tuple(n for n, f in DemoSummary.model_fields.items() if f.is_required())
OPTIONAL_FIELDS = tuple(n for n, f in DemoSummary.model_fields.items() if not f.is_required())


def _message(e: ErrorDetails) -> str:
    """Repair text for one validation error of a summary field (what the decision protocol
    says, `repair_message`, where a summary field needs no other words)."""
    kind, ctx, got = e["type"], e.get("ctx", {}), e.get("input")
    if kind == "extra_forbidden":
        return f"unknown field; valid fields: {', '.join(DemoSummary.model_fields)}"
    if kind == "string_too_long":
        return f"at most {ctx.get('max_length')} characters, got {len(str(got))}"
    if kind == "too_short":
        return f"must hold at least {ctx.get('min_length')} item(s)"
    if kind in ("string_type", "list_type", "dict_type"):
        return f"must be {_SHAPES[kind[:4].replace('stri', 'str')]}, got {show(got)}"
    if kind in ("greater_than_equal", "less_than_equal", "float_type", "float_parsing"):
        return f"must be a number between 0 and 1, got {show(got)}"
    if kind in ("missing", "string_too_short", "too_long", "literal_error", "value_error"):
        return repair_message(e)
    return str(e["msg"])


_SHAPES = {
    "str": "a string",
    "list": "a list of strings",
    "dict": 'an object {"left": ..., "right": ...}',
}


def _shape(value_or_tag: Any) -> str:
    """ "str", "list" or "dict": of a JSON value, or of a union branch tag ("list[...]")."""
    if isinstance(value_or_tag, str) and value_or_tag.startswith(("list[", "dict[")):
        return value_or_tag[:4]
    if isinstance(value_or_tag, list | dict):
        return "list" if isinstance(value_or_tag, list) else "dict"
    return "str"


def _problems(err: ValidationError, obj: dict[str, Any]) -> list[tuple[str, str]]:
    """(field, message) per problem, in schema order.

    A field whose type is a union (a string or a list) gets pydantic errors from every branch;
    only the branch matching the shape of the value the model sent speaks, and a value of no
    accepted shape gets one message listing the shapes."""
    by_field: dict[str, list[ErrorDetails]] = {}
    for e in err.errors():
        by_field.setdefault(str(e["loc"][0]) if e["loc"] else "", []).append(e)
    problems: list[tuple[str, str]] = []
    for name, errors in by_field.items():
        where = f"{SUMMARY_FIELD}.{name}" if name else SUMMARY_FIELD
        branches = [e for e in errors if len(e["loc"]) > 1 and isinstance(e["loc"][1], str)]
        if not branches or len(branches) < len(errors):  # not a union field
            branches = []
        if not branches:
            for e in errors:
                problems.append((where + _suffix(e["loc"][1:]), _message(e)))
            continue
        sent = _shape(obj.get(name))
        matching = [e for e in branches if _shape(e["loc"][1]) == sent]
        if not matching or all(
            len(e["loc"]) == 2 and e["type"].endswith("_type") for e in matching
        ):
            shapes = sorted({_shape(e["loc"][1]) for e in branches}, key=list(_SHAPES).index)
            valid = " or ".join(_SHAPES[s] for s in shapes)
            problems.append((where, f"must be {valid}, got {show(obj.get(name))}"))
            continue
        for e in matching:
            problems.append((where + _suffix(e["loc"][2:]), _message(e)))
    return problems


def _suffix(loc: Any) -> str:
    """The path below a field: list indices as [i], dict keys as .key ("[key]" markers dropped)."""
    out = ""
    for p in loc:
        if isinstance(p, int):
            out += f"[{p}]"
        elif p != "[key]":
            out += f".{p}"
    return out


def parse_summary(obj: Any) -> DemoSummary:
    """A validated summary, or `DecisionError` naming every problem (module docstring)."""
    if isinstance(obj, str):
        try:
            obj = json.loads(obj)
        except json.JSONDecodeError:
            raise DecisionError(
                SUMMARY_FIELD,
                "must be a JSON object with the summary fields, not free text; required: "
                + ", ".join(REQUIRED_FIELDS),
            ) from None
    if not isinstance(obj, dict):
        raise DecisionError(SUMMARY_FIELD, "must be a JSON object with the summary fields")
    try:
        summary = DemoSummary.model_validate(obj)
    except ValidationError as err:
        problems = _problems(err, obj)
        raise DecisionError(*problems[0], others=problems[1:]) from None
    text = summary_text(summary)
    if len(text) > MAX_SUMMARY_CHARS:
        raise DecisionError(
            SUMMARY_FIELD,
            f"too long: {len(text)} characters as shown to you later, at most "
            f"{MAX_SUMMARY_CHARS}; shorten the fields",
        )
    return summary


def _value_text(value: Any) -> str:
    if isinstance(value, list):
        return "; ".join(value)
    if isinstance(value, dict):
        return "; ".join(f"{arm}: {text}" for arm, text in value.items())
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def summary_text(summary: DemoSummary) -> str:
    """The compact text of a summary for every observation: a header line, then one line per
    field the model set ("- name: value", list items joined by "; "), in schema order.

    Every number in the text is one the model wrote: the header and field names hold none."""
    lines = [SUMMARY_HEADER]
    for name, value in summary.model_dump(exclude_none=True).items():
        lines.append(f"- {name}: {_value_text(value)}")
    return "\n".join(lines)
