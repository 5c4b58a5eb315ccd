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


def plain_message(e: ErrorDetails) -> str:
    """Pydantic's own message for a person, with the value that was given."""
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
