"""The privilege boundary: what the model may see, and a checker for what it must never see.

This module is the one place that lists the model-visible observation fields (spec FACTS.md,
"Observation sent each decision"). Everything else the simulator and the tasks know (object
names, poses and sizes, seeds, contact and checker state, latched flags, camera calibration,
object model ids) is evaluator-only.

Two halves:

- `filter_proprio(proprio, arms)` takes the per-arm dicts of `sim_mjx.layout.proprio_fields` and
  returns exactly the visible fields, in a fixed order; any extra or missing key raises
  `VisibilityError` naming it. The observation builder goes through it, so an evaluator field
  added to the simulator's dict fails loudly instead of reaching a prompt.
- `find_leaks(body, secrets)` / `assert_model_visible(body, secrets)` scan what a model would
  read in a request (a `ChatRequest`, a provider request body as dict or JSON text) for
  evaluator-only identifiers and for the numbers of `secrets` (an object's position, the seed,
  the camera's position). It reads only model-visible text: system and user content. Images
  (base64) are skipped, and so are assistant turns: they are the model's own words, and a leak
  can only reach them through the system or user content that is scanned. The values of the
  visible robot-state fields are also skipped before number matching, because the gripper
  legitimately sits at an object's position when it grasps it.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

# ------------------------------------------------------------------------------------------
# Model-visible fields
# ------------------------------------------------------------------------------------------

PROPRIO_FIELDS: tuple[str, ...] = (
    "is_open",
    "finger_center_xyz",
    "control_eepose_xyz",
    "control_eepose_rpy_deg",
    "control_eepose_quat",
    "local_axes_world",
)
"""Per-arm proprioception produced by the simulator (`sim_mjx.layout.proprio_fields`)."""

FEEDBACK_FIELDS: tuple[str, ...] = ("last_action_valid", "last_planner_success")
"""Per-arm outcome of the previous action, added by the harness (None before the first one)."""

ARM_FIELDS: tuple[str, ...] = PROPRIO_FIELDS + FEEDBACK_FIELDS
"""Everything the model sees about one arm, in display order."""

LOCAL_AXES: tuple[str, ...] = ("rx", "ry", "rz")

OBSERVATION_FIELDS: tuple[str, ...] = (
    "step",
    "instruction",
    "gripper_state",
    "self_geometry",
    "executed_actions",
    "history_steps",
    "available_actions",
    "demonstration_summary",
)
"""The fields of one observation (besides its image or images): the gripper state and the
self-geometry are derived from `ARM_FIELDS` alone (`observation.self_geometry`)."""

_VECTOR_LENGTHS = {
    "finger_center_xyz": 3,
    "control_eepose_xyz": 3,
    "control_eepose_rpy_deg": 3,
    "control_eepose_quat": 4,
}


class VisibilityError(ValueError):
    """A field outside the model-visible set, or a visible field of the wrong shape."""

    def __init__(self, field: str, message: str):
        super().__init__(f"observation field '{field}': {message}")
        self.field = field


def _vector(value: Any, n: int, field: str) -> list[float]:
    if isinstance(value, str | bytes) or not isinstance(value, Sequence) or len(value) != n:
        raise VisibilityError(field, f"expected {n} numbers, got {value!r}")
    out = []
    for x in value:
        if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
            raise VisibilityError(field, f"expected finite numbers, got {value!r}")
        out.append(float(x))
    return out


def _check_keys(got: Mapping[str, Any], expected: Sequence[str], where: str) -> None:
    extra = [k for k in got if k not in expected]
    if extra:
        raise VisibilityError(f"{where}.{extra[0]}", "not a model-visible field")
    missing = [k for k in expected if k not in got]
    if missing:
        raise VisibilityError(f"{where}.{missing[0]}", "missing")


def filter_proprio(
    proprio: Mapping[str, Mapping[str, Any]], arms: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """The visible proprioception of the task's `arms`, validated and in display order.

    `proprio` maps arm name -> the fields of `PROPRIO_FIELDS` (as `proprio_fields` makes them).
    Raises `VisibilityError` naming the field for an arm other than `arms`, a key outside
    `PROPRIO_FIELDS` (an object pose, a contact flag...), a missing key, or a value of the
    wrong shape. Values are copied, never shared with the caller.
    """
    _check_keys(proprio, arms, "robot")
    out: dict[str, dict[str, Any]] = {}
    for arm in arms:
        fields = proprio[arm]
        if not isinstance(fields, Mapping):
            raise VisibilityError(f"robot.{arm}", f"expected a mapping, got {type(fields)}")
        _check_keys(fields, PROPRIO_FIELDS, f"robot.{arm}")
        is_open = fields["is_open"]
        if not isinstance(is_open, bool):
            raise VisibilityError(f"robot.{arm}.is_open", f"expected a bool, got {is_open!r}")
        clean: dict[str, Any] = {"is_open": is_open}
        for key, n in _VECTOR_LENGTHS.items():
            clean[key] = _vector(fields[key], n, f"robot.{arm}.{key}")
        axes = fields["local_axes_world"]
        if not isinstance(axes, Mapping):
            raise VisibilityError(f"robot.{arm}.local_axes_world", "expected {rx, ry, rz}")
        _check_keys(axes, LOCAL_AXES, f"robot.{arm}.local_axes_world")
        clean["local_axes_world"] = {
            k: _vector(axes[k], 3, f"robot.{arm}.local_axes_world.{k}") for k in LOCAL_AXES
        }
        out[arm] = clean
    return out


# ------------------------------------------------------------------------------------------
# Evaluator-only vocabulary
# ------------------------------------------------------------------------------------------

EVALUATOR_ONLY_TERMS: tuple[str, ...] = (
    # scene state and object geometry
    "object_pose",
    "object_poses",
    "object_pos",
    "object_position",
    "object_quat",
    "object_size",
    "obj_pos",
    "obj_pose",
    "initial_pose",
    "init_qpos",
    "qpos",
    "qvel",
    "xpos",
    "xquat",
    "half_size",
    "halfsize",
    # seeds and object models
    "seed",
    "seeds",
    "variant",
    "variants",
    "variant_id",
    "model_id",
    # checker state
    "latch",
    "latched",
    "latches",
    "checkpoint",
    "checkpoints",
    "subgoal",
    "subgoals",
    "predicate",
    "checker",
    "contact_flags",
    "contact_pairs",
    "in_contact",
    # camera calibration
    "fov",
    "fovy",
    "field of view",
    "intrinsic",
    "intrinsics",
    "extrinsic",
    "extrinsics",
    "focal",
    "camera_pos",
    "camera_position",
    "cam_pos",
    # privileged sources
    "ground truth",
    "ground_truth",
    "oracle",
    "privileged",
    "evaluator",
)
"""Identifiers and phrases that never appear in model-visible text written by the harness
(matched case-insensitively as whole words; an underscore counts as a separator, so
`seed_1003` matches `seed`). The system prompt is written to avoid them all."""

EVALUATOR_ONLY_KEYS: tuple[str, ...] = (
    "contact",
    "contacts",
    "success",
    "checks",
    "progress",
    "size",
    "sizes",
    "pos",
    "quat",
    "pose",
    "poses",
    "object",
    "objects",
    "target",
)
"""Common words that are evaluator data only as a key of a record (`"success": true`,
`pos=[...]`), so they are matched only with a quote before them and a colon after, or with
`=` after, never as prose ("make contact", "task progress")."""


def _term_pattern(terms: Sequence[str]) -> re.Pattern[str]:
    alternatives = "|".join(re.escape(t).replace(r"\ ", r"[\s_-]+") for t in terms)
    return re.compile(rf"(?<![A-Za-z0-9])(?:{alternatives})(?![A-Za-z0-9])", re.IGNORECASE)


def _key_pattern(keys: Sequence[str]) -> re.Pattern[str]:
    alternatives = "|".join(re.escape(k) for k in keys)
    return re.compile(
        rf"""(?:["'](?:{alternatives})["']\s*:|(?<![A-Za-z0-9_.])(?:{alternatives})\s*=)""",
        re.IGNORECASE,
    )


_TERMS = _term_pattern(EVALUATOR_ONLY_TERMS)
_KEYS = _key_pattern(EVALUATOR_ONLY_KEYS)
_NUMBER = re.compile(r"(?<![A-Za-z0-9.])-?\d+(?:\.\d+)?(?!\.?\d)")
_DATA_URL = re.compile(r"data:[A-Za-z/+.-]+;base64,[A-Za-z0-9+/=]*")
_BASE64_RUN = re.compile(r"[A-Za-z0-9+/=]{200,}")
# The visible robot state legitimately holds numbers near an object's position (a gripper at
# the object it grasps); their values are removed before number matching, keys kept.
_VISIBLE_VALUES = re.compile(
    r"""(["']?(?:finger_center_xyz|control_eepose_xyz|control_eepose_rpy_deg|"""
    r"""control_eepose_quat|control_eepose_quat_wxyz|grip_center_direction_world)"""
    r"""["']?\s*[:=]\s*)\[[^\]]*\]"""
    r"""|(["']?(?:local_axes_world|grip_center_angle_to_world_axes_deg)["']?\s*[:=]\s*)"""
    r"""\{[^}]*\}"""
    r"""|(["']?(?:grip_center_length_m|grip_center_angle_to_table_down_deg)["']?\s*:\s*)"""
    r"""-?[\d.]+"""
)


# ------------------------------------------------------------------------------------------
# Secrets: evaluator-only numbers of one episode
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Secret:
    """Numbers the model must not read, e.g. an object's initial position.

    A vector matches a run of consecutive numbers in the text (whatever separates them) within
    `tolerance` of `values`, in the given units or scaled by each of `scales` (a position in
    metres also matches when written in millimetres). A single integer matches an integer
    token equal to it (used for seeds). A `word` matches that identifier.
    """

    name: str
    values: tuple[float, ...] = ()
    tolerance: float = 0.0
    scales: tuple[float, ...] = (1.0,)
    word: str | None = None
    """Instead of numbers: an identifier (an object model id such as "shoe_3", a latch name
    such as "giver_grasped") matched as a whole word, case-insensitively."""


POSITION_TOLERANCE_M = 0.0005
"""Half a millimetre: catches a position rounded to 3 decimals (m) or 0.5 mm, and is far below
how closely an unaided model places numbers by chance."""

MIN_SEED_DIGITS = 4
"""Seeds with fewer digits are matched by the `seed` identifier only: a bare small integer
("step 12") is not evidence of a leak."""


def episode_secrets(
    object_positions: Mapping[str, Sequence[float]] | None = None,
    seed: int | None = None,
    camera_positions: Mapping[str, Sequence[float]] | None = None,
    identifiers: Sequence[str] = (),
) -> list[Secret]:
    """The secrets of one episode: each object's position and each camera's position (metres,
    matched in m and mm), the seed if it has at least `MIN_SEED_DIGITS` digits, and the
    `identifiers` that contain an underscore or a digit (plain words such as "cube" or
    "grasped" also belong to the instruction and to prose, so they cannot tell a leak).

    For a task and a seed:
    `episode_secrets({n: pos for n, (pos, _) in task.sample(seed).poses.items()}, seed,
    {"head": HEAD_CAMERA_POS}, [*task.variants, *task.latches, *task.checkpoints])`.
    """
    secrets = [
        Secret(f"identifier {word}", word=word)
        for word in dict.fromkeys(identifiers)
        if "_" in word or any(c.isdigit() for c in word)
    ]
    for kind, positions in (("object", object_positions), ("camera", camera_positions)):
        for name, pos in (positions or {}).items():
            values = tuple(float(v) for v in pos)
            secrets.append(
                Secret(f"{kind} {name} position", values, POSITION_TOLERANCE_M, (1.0, 1000.0))
            )
    if seed is not None and len(str(abs(int(seed)))) >= MIN_SEED_DIGITS:
        secrets.append(Secret("seed", (float(seed),)))
    return secrets


# ------------------------------------------------------------------------------------------
# Leak detection
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Leak:
    kind: str  # "term", "key", "value" or "identifier"
    what: str  # the matched identifier, or the secret's name
    where: str  # which message of the request
    excerpt: str

    def __str__(self) -> str:
        return f"{self.kind} {self.what!r} in {self.where}: ...{self.excerpt}..."


class PrivilegeLeak(AssertionError):
    """Evaluator-only information in a model-visible request."""

    def __init__(self, leaks: Sequence[Leak]):
        super().__init__(
            "evaluator-only information reaches the model:\n  "
            + "\n  ".join(str(leak) for leak in leaks)
        )
        self.leaks = list(leaks)


_SKIPPED_KEYS = frozenset(
    {"image_url", "source", "url", "data", "media_type", "type", "role", "cache_control", "id"}
)
_MESSAGE_KEYS = ("system", "instructions", "messages", "input")


def _strings(node: Any, where: str) -> Iterator[tuple[str, str]]:
    """(where, text) of every model-visible string below `node`, skipping assistant messages
    and image payloads."""
    if isinstance(node, str):
        if not node.startswith("data:"):
            yield where, node
    elif isinstance(node, Mapping):
        if node.get("role") == "assistant":
            return
        role = node.get("role")
        here = f"{where}({role})" if isinstance(role, str) else where
        for key, value in node.items():
            if key not in _SKIPPED_KEYS:
                yield from _strings(value, f"{here}.{key}")
    elif isinstance(node, list | tuple):
        for i, value in enumerate(node):
            yield from _strings(value, f"{where}[{i}]")


def visible_texts(body: Any) -> list[tuple[str, str]]:
    """The model-visible text of a request as (where, text) pairs.

    `body` is a `ChatRequest`, a provider request body (OpenAI Chat / Responses, Anthropic
    Messages) as a dict, or such a body as JSON text; other text is taken whole with data URLs
    and long base64 runs removed. Generation parameters of a provider body (model, max_tokens,
    an API sampling seed...) are not read: the model never sees them as text.
    """
    from vabench.llm_pool.messages import ChatRequest  # the pool imports nothing of ours

    if isinstance(body, ChatRequest):
        out = [("system", body.system)] if body.system else []
        for i, turn in enumerate(body.turns):
            if turn.role == "user":
                out += [(f"turns[{i}]", p) for p in turn.content if isinstance(p, str)]
        return out
    if isinstance(body, bytes):
        body = body.decode("utf-8", errors="replace")
    if isinstance(body, str):
        try:
            body = json.loads(body)
        except ValueError:
            return [("text", _BASE64_RUN.sub("", _DATA_URL.sub("", body)))]
    if isinstance(body, Mapping) and any(k in body for k in _MESSAGE_KEYS):
        return [s for k in _MESSAGE_KEYS if k in body for s in _strings(body[k], k)]
    return list(_strings(body, "body"))


def _excerpt(text: str, start: int, end: int, margin: int = 40) -> str:
    return text[max(0, start - margin) : end + margin].replace("\n", " ")


def _secret_match(secret: Secret, numbers: Sequence[tuple[str, float]]) -> int | None:
    """Index of the first token where `secret` occurs in the text's numeric tokens."""
    n = len(secret.values)
    if n == 1:  # an integer: exact, and only as an integer token
        return next(
            (i for i, (tok, x) in enumerate(numbers) if "." not in tok and x == secret.values[0]),
            None,
        )
    for i in range(len(numbers) - n + 1):
        window = [x for _, x in numbers[i : i + n]]
        for scale in secret.scales:
            tol = secret.tolerance * scale
            if all(abs(w - v * scale) <= tol for w, v in zip(window, secret.values, strict=True)):
                return i
    return None


def _value_leaks(text: str, where: str, secrets: Sequence[Secret]) -> Iterator[Leak]:
    text = _VISIBLE_VALUES.sub(lambda m: m.group(1) or m.group(2) or m.group(3), text)
    tokens = list(_NUMBER.finditer(text))
    numbers = [(t.group(), float(t.group())) for t in tokens]
    for secret in secrets:
        if secret.word is not None:
            continue
        i = _secret_match(secret, numbers)
        if i is not None:
            last = tokens[i + len(secret.values) - 1]
            yield Leak("value", secret.name, where, _excerpt(text, tokens[i].start(), last.end()))


def find_leaks(body: Any, secrets: Sequence[Secret] = ()) -> list[Leak]:
    """Evaluator-only identifiers, record keys and secret numbers in the model-visible text of
    `body` (see `visible_texts`). An empty list means the request is clean."""
    leaks: list[Leak] = []
    for where, text in visible_texts(body):
        for pattern, kind in ((_TERMS, "term"), (_KEYS, "key")):
            for m in pattern.finditer(text):
                leaks.append(Leak(kind, m.group(), where, _excerpt(text, m.start(), m.end())))
        leaks.extend(_value_leaks(text, where, secrets))
        for secret in secrets:
            if secret.word is not None:
                found = _term_pattern([secret.word]).search(text)
                if found:
                    excerpt = _excerpt(text, found.start(), found.end())
                    leaks.append(Leak("identifier", secret.name, where, excerpt))
    return leaks


def assert_model_visible(body: Any, secrets: Sequence[Secret] = ()) -> None:
    """Raise `PrivilegeLeak` listing every leak `find_leaks` finds in `body`."""
    leaks = find_leaks(body, secrets)
    if leaks:
        raise PrivilegeLeak(leaks)
