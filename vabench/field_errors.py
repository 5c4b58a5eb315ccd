"""Pydantic's validation errors as (field, problem) pairs, one per error.

Two audiences read them: a model repairing its reply (`vabench.protocol`) and a person fixing a
config file (`vabench.config`, `vabench.llm_pool.config`). Each words the problem its own way
(the `message` function); the field is written the same way for both, `models[1].limits.rpm`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from pydantic import ValidationError
from pydantic_core import ErrorDetails


def dotted(loc: Iterable[Any], prefix: str = "", whole: str = "") -> str:
    """A pydantic location as a field path under `prefix` (`whole` when it is empty)."""
    out = prefix
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or whole


def shorten(value: Any, limit: int = 60) -> str:
    """`repr(value)`, cut to `limit` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


_SENTENCES = {
    "greater_than_equal": "must be at least {ge}",
    "greater_than": "must be more than {gt}",
    "less_than_equal": "must be at most {le}",
    "less_than": "must be less than {lt}",
    "int_parsing": "must be a whole number",
    "int_type": "must be a whole number",
    "int_from_float": "must be a whole number",
    "float_parsing": "must be a number",
    "float_type": "must be a number",
    "bool_parsing": "must be true or false",
    "bool_type": "must be true or false",
    "string_type": "must be text",
    "list_type": "must be a list",
    "dict_type": "must be a mapping of settings",
    "model_type": "must be a mapping of settings",
    "model_attributes_type": "must be a mapping of settings",
    "literal_error": "must be {expected}",
    "enum": "must be {expected}",
    "missing": "is required",
    "too_short": "must hold at least {min_length} {items}",
    "too_long": "must hold at most {max_length} {items}",
    "string_too_short": "must be at least {min_length} {characters} long",
    "string_too_long": "must be at most {max_length} {characters} long",
}
"""Pydantic's error types as the sentence a person reads (its own "Input should be greater than
or equal to 1" names neither the field nor what to write); other types keep pydantic's words."""


def plain_message(e: ErrorDetails) -> str:
    """The problem for a person, with the value that was given: "must be at least 1, got 0"."""
    template = _SENTENCES.get(e["type"])
    ctx = dict(e.get("ctx", {}))
    one = ctx.get("min_length", ctx.get("max_length")) == 1
    ctx.update(items="item" if one else "items", characters="character" if one else "characters")
    try:
        message = template.format(**ctx) if template else None
    except (KeyError, IndexError):  # a context without the figure: pydantic's own words
        message = None
    if message is None:
        message = e["msg"].removeprefix("Value error, ")
    if e["type"] not in ("missing", "value_error") and "input" in e:
        message += f", got {shorten(e['input'])}"
    return message


def field_problems(
    err: ValidationError,
    message: Callable[[ErrorDetails], str] = plain_message,
    *,
    prefix: str = "",
    whole: str = "",
) -> list[tuple[str, str]]:
    """(field, problem) for every error of `err`, fields under `prefix` (`whole` for the
    object itself), problems worded by `message`."""
    return [(dotted(e["loc"], prefix, whole), message(e)) for e in err.errors()]
