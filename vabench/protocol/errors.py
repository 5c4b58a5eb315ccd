"""What a model is told when its reply is not a valid decision.

`DecisionError(field, message)` is raised by every parser of this package; `str(error)` is the
repair text sent back to the model. Pydantic's errors are turned into that text here, naming
the field, what is valid and what the model sent (`decision_error`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from pydantic import ValidationError
from pydantic_core import ErrorDetails

from vabench.field_errors import field_problems
from vabench.protocol.vocabulary import ANGLE_DEG, DISTANCE_MM, TOOL_NAMES

REPLY = "reply"
"""The `DecisionError.field` of problems with the reply as a whole (no JSON, invalid JSON)."""


class DecisionError(ValueError):
    """A reply that cannot be turned into a decision.

    `field` names the offending field ("reply" for the reply as a whole, "args.step" inside a
    tool's arguments, "right.distance_mm" inside a dual move); `message` says what is wrong and
    what is valid. `str(error)` is the repair text for the model; when several fields are wrong
    at once, `others` holds the rest and `str` lists them all, so one repair can fix them all.
    """

    def __init__(self, field: str, message: str, others: Sequence[tuple[str, str]] = ()):
        self.field = field
        self.message = message
        self.others = tuple(others)
        parts = [message if field == REPLY else f"field '{field}': {message}"]
        parts += [f"field '{f}': {m}" for f, m in self.others]
        super().__init__("; ".join(parts))


ActionError = DecisionError
"""The name the simulator side uses; one concept, one class."""


def show(value: Any) -> str:
    """A value as the model wrote it (JSON), shortened for repair text."""
    text = json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


_BOUNDS = {"distance_mm": DISTANCE_MM, "angle_deg": ANGLE_DEG}


def repair_message(e: ErrorDetails) -> str:
    """Repair text for one pydantic error: what is valid, and what the model sent."""
    kind, ctx = e["type"], e.get("ctx", {})
    got = e.get("input")
    name = str(e["loc"][-1]) if e["loc"] else ""
    if kind == "missing":
        return "required"
    if kind in ("greater_than_equal", "less_than_equal", "greater_than", "less_than"):
        if name in _BOUNDS:
            low, high = _BOUNDS[name]
            return f"must be between {low:g} and {high:g}, got {show(got)}"
        bound = next(iter(ctx.items()), ("", ""))
        op = {"ge": ">=", "le": "<=", "gt": ">", "lt": "<"}.get(bound[0], bound[0])
        return f"must be {op} {bound[1]}, got {show(got)}"
    if kind == "literal_error":
        if name == "sign":
            return (
                "must be '+' or '-' (also accepted: pos, positive, ccw, +1, 1, neg, negative, "
                "cw, -1), "
                f"got {show(got)}"
            )
        return f"must be {ctx.get('expected')}, got {show(got)}"
    if kind in ("float_type", "float_parsing", "finite_number"):
        return f"must be a number, got {show(got)}"
    if kind in ("int_type", "int_parsing", "int_from_float"):
        return f"must be an integer, got {show(got)}"
    if kind == "string_too_short":
        return "must not be empty"
    if kind == "string_type":
        return f"must be a string, got {show(got)}"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return f"must be a JSON object, got {show(got)}"
    if kind == "list_type":
        return f"must be a list, got {show(got)}"
    if kind == "too_long":
        return f"must hold at most {ctx.get('max_length')} items, got {ctx.get('actual_length')}"
    if kind == "too_short":
        return f"must hold at least {ctx.get('min_length')} item(s), got {ctx.get('actual_length')}"
    if kind == "value_error":
        return str(ctx.get("error", e["msg"]))
    return e["msg"]


def decision_error(err: ValidationError, prefix: str = "") -> DecisionError:
    """One `DecisionError` listing every problem of `err`, fields dotted under `prefix`."""
    problems = field_problems(err, repair_message, prefix=prefix, whole="action")
    return DecisionError(*problems[0], others=problems[1:])


def unknown_action(name: Any, valid: Sequence[str]) -> DecisionError:
    """An action name that is not one of `valid`, with a hint when it names a tool or stop."""
    if not isinstance(name, str):
        return DecisionError("action", f"must be a string naming the action, got {show(name)}")
    hint = ""
    if name in TOOL_NAMES:
        hint = f'; \'{name}\' is a tool: {{"tool": "{name}", "args": {{...}}}}'
    elif name == "stop":
        hint = '; to stop, reply {"stop": true}'
    return DecisionError(
        "action", f"unknown action {show(name)}{hint}; valid actions: {', '.join(valid)}"
    )
