"""Check a JSON value against an official SDK's parameter type (a TypedDict), strictly.

The `openai` and `anthropic` SDKs describe every request body as TypedDicts whose keys are the
API's parameters. pydantic validates TypedDicts but ignores keys they do not declare, which is
exactly the mistake to catch (a parameter the API version no longer takes), so this walks the
type itself: unknown keys, missing required keys, literals, unions, lists and primitives.
`problems(value, T)` returns one line per mismatch, naming its path; [] means it conforms.
"""

from __future__ import annotations

import collections.abc as cabc
import types
import typing
from typing import Any, Literal, Union, get_args, get_origin

from typing_extensions import NotRequired, Required, is_typeddict

_SEQUENCES = (list, cabc.Iterable, cabc.Sequence, typing.Iterable, typing.Sequence)


def problems(value: Any, tp: Any, path: str = "body") -> list[str]:
    origin = get_origin(tp)
    args = get_args(tp)
    if tp is Any or tp is object:
        return []
    if origin is typing.Annotated:
        return problems(value, args[0], path)
    if origin in (Required, NotRequired):
        return problems(value, args[0], path)
    if origin in (Union, types.UnionType):
        best: list[str] | None = None
        for arm in args:
            found = problems(value, arm, path)
            if not found:
                return []
            if best is None or _depth(found) > _depth(best):
                best = found
        return best or [f"{path}: matches no type of {tp}"]
    if tp is type(None):
        return [] if value is None else [f"{path}: expected null, got {value!r:.60}"]
    if origin is Literal:
        return [] if value in args else [f"{path}: {value!r:.60} is not one of {args}"]
    if is_typeddict(tp):
        return _typeddict(value, tp, path)
    if origin in (dict, cabc.Mapping, typing.Dict) or tp is dict:  # noqa: UP006
        if not isinstance(value, dict):
            return [f"{path}: expected an object"]
        inner = args[1] if len(args) == 2 else Any
        return [p for k, v in value.items() for p in problems(v, inner, f"{path}.{k}")]
    if origin in _SEQUENCES or (origin is not None and _is_sequence_alias(origin)):
        if not isinstance(value, list):
            return [f"{path}: expected an array, got {type(value).__name__}"]
        inner = args[0] if args else Any
        return [p for i, v in enumerate(value) for p in problems(v, inner, f"{path}.{i}")]
    if tp is str:
        return [] if isinstance(value, str) else [f"{path}: expected a string"]
    if tp is bool:
        return [] if isinstance(value, bool) else [f"{path}: expected a boolean"]
    if tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
        return [] if ok else [f"{path}: expected an integer"]
    if tp is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        return [] if ok else [f"{path}: expected a number"]
    return [f"{path}: cannot check against {tp!r} (extend tests/sdk_types.py)"]


def _is_sequence_alias(origin: Any) -> bool:
    return getattr(origin, "__name__", "") in ("SequenceNotStr", "Iterable", "Sequence")


def _depth(found: list[str]) -> int:
    """How far into the value the deepest problem got (to report the closest union arm)."""
    return max(p.split(":", 1)[0].count(".") for p in found)


def _typeddict(value: Any, tp: Any, path: str) -> list[str]:
    if not isinstance(value, dict):
        return [f"{path}: expected an object ({tp.__name__})"]
    hints = typing.get_type_hints(tp, include_extras=True)
    out = [f"{path}.{key}: not a parameter of {tp.__name__}" for key in value if key not in hints]
    # `__required_keys__` misses Required[...] written as a string annotation (the SDKs use
    # `from __future__ import annotations`): read it from the resolved hints.
    total = getattr(tp, "__total__", True)
    required = {
        key
        for key, hint in hints.items()
        if get_origin(hint) is Required or (total and get_origin(hint) is not NotRequired)
    }
    out += [
        f"{path}.{key}: required by {tp.__name__}, missing"
        for key in sorted(required)
        if key not in value
    ]
    for key, v in value.items():
        if key in hints:
            out += problems(v, hints[key], f"{path}.{key}")
    return out
