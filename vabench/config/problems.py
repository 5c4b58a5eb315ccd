"""Everything wrong with a config file, one line a problem: `error: <file>: <field>: <problem>`
(the one form of the command's errors: "error: WHAT: WHY; FIX").

Pydantic's and YAML's errors are turned into `Problem`s here; a misspelt key or name gets a
"did you mean" from the fields or names that exist.
"""

from __future__ import annotations

import difflib
import types
import typing
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from vabench.field_errors import dotted, plain_message
from vabench.llm_pool.config import ConfigError


@dataclass(frozen=True)
class Problem:
    path: str
    """Dotted field path (`models[1].limits.rpm`), or `line L, column C` for YAML syntax."""
    message: str


class SweepConfigError(ValueError):
    """Everything wrong with one config file: one line `error: <file>: <field>: <problem>`
    each."""

    def __init__(self, file: str, problems: Iterable[Problem]):
        self.file = file
        self.problems = list(problems)
        lines = [
            f"error: {file}: {p.path}: {p.message}" if p.path else f"error: {file}: {p.message}"
            for p in self.problems
        ]
        super().__init__("\n".join(lines))


def is_int(value: Any) -> bool:
    """A whole number that is not a boolean (YAML's `true` is no count)."""
    return isinstance(value, int) and not isinstance(value, bool)


def unknown(kind: str, name: str, valid: Iterable[str]) -> str:
    """ "unknown <kind> 'name'" with the closest valid name, or the list of valid ones."""
    valid = list(valid)
    close = difflib.get_close_matches(name, valid, n=1)
    if close:
        return f"unknown {kind} {name!r}; did you mean {close[0]!r}?"
    return f"unknown {kind} {name!r}; valid: {', '.join(valid)}"


def pydantic_problems(err: ValidationError, schema: type[BaseModel]) -> list[Problem]:
    """One `Problem` per error of `err` raised validating `schema`: unknown keys name the
    valid ones, an endpoint's own `ConfigError` keeps its field and message."""
    problems = []
    for e in err.errors():
        loc = tuple(e["loc"])
        ctx_error = e.get("ctx", {}).get("error")
        if isinstance(ctx_error, ConfigError):  # raised inside an endpoint validator
            problems.append(
                Problem(dotted(loc + tuple(ctx_error.field.split("."))), ctx_error.message)
            )
        elif e["type"] == "extra_forbidden":
            valid = _field_names(schema, loc[:-1])
            problems.append(Problem(dotted(loc), unknown("field", str(loc[-1]), valid)))
        else:
            problems.append(Problem(dotted(loc), plain_message(e)))
    return problems


def _field_names(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    """The field names of the pydantic model found at `loc` under `model` (for suggestions)."""
    node: Any = model
    for part in loc:
        if isinstance(part, int):
            node = _inner(node, list)
            continue
        if not (isinstance(node, type) and issubclass(node, BaseModel)):
            node = _inner(node, dict)
            continue
        field = node.model_fields.get(part)
        if field is None:
            return []
        node = _unwrap(field.annotation)
    return list(node.model_fields) if isinstance(node, type) and issubclass(node, BaseModel) else []


def _unwrap(annotation: Any) -> Any:
    """`X | None` -> X."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return args[0] if len(args) == 1 else annotation
    return annotation


def _inner(annotation: Any, container: type) -> Any:
    """The item type of list[X] (or the value type of dict[K, X])."""
    args = typing.get_args(_unwrap(annotation))
    return (
        _unwrap(args[-1]) if typing.get_origin(_unwrap(annotation)) is container and args else None
    )


def yaml_problem(err: yaml.MarkedYAMLError) -> Problem:
    """A YAML syntax error at its line and column."""
    mark = err.problem_mark or err.context_mark
    where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
    what = " ".join(s for s in (err.context, err.problem) if s)
    return Problem(where, f"YAML syntax error: {what}")
