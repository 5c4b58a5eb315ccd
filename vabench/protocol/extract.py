"""The decision object of a model reply, found in free text.

A fenced block tagged json wins over bare text; with several, the LAST one is taken, because
models that think aloud show drafts and alternatives first and commit at the end. Untagged
fences count only when no json-tagged one exists and their body starts with "{"; fences of
other languages are ignored. Without a fence, the top-level balanced {...} spans of the text
are found (braces inside JSON strings do not count; an unmatched prose "{" is skipped), and the
last one that decodes to an object with an "action", "tool" or "stop" key is taken (else the
last object). A chosen block that does not decode is an error, never a silent fall-back to an
earlier draft.
"""

from __future__ import annotations

import json
import re
from typing import Any

from vabench.protocol.errors import REPLY, DecisionError

_FENCE = re.compile(r"```([^\n`]*)(.*?)```", re.S)
_DECISION_KEYS = ("action", "tool", "stop")


def _fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language tag, body) of every ``` fence; `json{...}` on the fence line is body."""
    blocks = []
    for m in _FENCE.finditer(text):
        header = re.match(r"\s*([A-Za-z][\w+.-]*)?(.*)", m[1], re.S)
        assert header is not None  # the pattern matches every string
        blocks.append(((header[1] or "").lower(), (header[2] or "") + m[2]))
    return blocks


def _balanced_spans(text: str) -> tuple[list[tuple[int, int]], bool]:
    """Top-level {...} spans of free text, with braces inside JSON strings ignored.

    A "{" that is never closed (prose, or a reply cut off) is skipped and the scan resumes
    after it, so it cannot swallow the real object; the flag says one was seen.
    """
    spans: list[tuple[int, int]] = []
    unclosed = False
    pos = 0
    while (start := text.find("{", pos)) >= 0:
        depth, in_string, escaped, end = 0, False, False, -1
        for i in range(start, len(text)):
            ch = text[i]
            if in_string:
                if escaped:
                    escaped = False
                elif ch == "\\":
                    escaped = True
                elif ch == '"':
                    in_string = False
            elif ch == '"':
                in_string = True
            elif ch == "{":
                depth += 1
            elif ch == "}":
                depth -= 1
                if depth == 0:
                    end = i + 1
                    break
        if end < 0:
            unclosed = True
            pos = start + 1
        else:
            spans.append((start, end))
            pos = end
    return spans, unclosed


def _decode(body: str, where: str) -> Any:
    try:
        return json.loads(body)
    except json.JSONDecodeError as err:
        raise DecisionError(
            REPLY, f"{where} is not valid JSON: {err.msg} at line {err.lineno} column {err.colno}"
        ) from None


def as_object(value: Any, where: str) -> dict[str, Any]:
    """`value` if it is a JSON object, else a `DecisionError` saying what it is."""
    if not isinstance(value, dict):
        kind = {list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
            type(value), "a number"
        )
        raise DecisionError(REPLY, f"{where} must be one JSON object, got {kind}")
    return value


def extract_json_object(text: str) -> dict[str, Any]:
    """The decision object of a reply (module docstring)."""
    if not text.strip():
        raise DecisionError(REPLY, "the reply is empty; reply with one JSON object")
    blocks = _fenced_blocks(text)
    tagged = [body for tag, body in blocks if tag.startswith("json")]
    untagged = [body for tag, body in blocks if not tag and body.lstrip().startswith("{")]
    if tagged or untagged:
        body = (tagged or untagged)[-1]
        return as_object(_decode(body.strip(), "the ```json block"), "the ```json block")
    try:
        whole = json.loads(text)
    except json.JSONDecodeError:
        pass
    else:
        return as_object(whole, "the reply")
    spans, unclosed = _balanced_spans(text)
    objects = []
    for start, end in spans:
        try:
            value = json.loads(text[start:end])
        except json.JSONDecodeError:
            continue
        if isinstance(value, dict):
            objects.append(value)
    decisions = [o for o in objects if any(k in o for k in _DECISION_KEYS)]
    if decisions or objects:
        return (decisions or objects)[-1]
    if spans:  # none decodes: report on the last one that looks like a decision
        bodies = [text[start:end] for start, end in spans]
        meant = [b for b in bodies if any(f'"{k}"' in b for k in _DECISION_KEYS)]
        _decode((meant or bodies)[-1], "the JSON object in the reply")
    if unclosed:
        raise DecisionError(
            REPLY,
            "the reply has a '{' without a matching '}' (cut off?); reply with one JSON object",
        )
    raise DecisionError(REPLY, "no JSON object found in the reply")
