"""An automatic annotator: a model judges episodes through the LLM pool, in the paper's two
stages, and its judgments are written exactly as a human annotator's are (one JSONL file per
judge, `source: judge:<model>`), so human and model judges meet in the same agreement table.

Each of `judges` independent judges (annotators `judge-<model>-<k>`) gets, per episode, one
conversation:
1. the system prompt (the rubric) and a transcript of what the model under test saw and did,
   with its images; it answers the two gates;
2. once every judge has answered, the gates are decided by majority over all annotators of the
   episode (human votes included), and each judge is asked, in the same conversation, for the
   criteria that majority activates.

The privilege boundary: the transcript is built only from model-visible fields (the task
instruction, the images the model saw, its replies and parsed decisions, validity and planner
feedback, tool results, the robot state of the observation). Object poses, predicate checks,
checkpoint progress, success, clipping and the seed never enter a prompt; a test scans every
captured request with `vabench.agent.visibility.find_leaks`.
"""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vabench.diagnostics.criteria import CRITERIA, CRITERION_CODES, GATE_CODES, GATES
from vabench.diagnostics.episodes import RunIndex, task_instruction
from vabench.diagnostics.store import (
    AnnotationError,
    AnnotationStore,
    Judgment,
    current,
    gate_votes,
    majority,
)
from vabench.llm_pool import ChatRequest, Image, LLMPool, Turn
from vabench.llm_pool.errors import InfrastructureError, RequestRejected

JUDGE_MARK = "You are an annotator of VA-Bench robot-manipulation episodes."
"""First line of the judge's system prompt (the embedded `rubric_judge` policy keys on it)."""
STAGE_ONE = "Stage one"
STAGE_TWO = "Stage two"
MAX_REPAIRS = 2
MAX_REPLY_CHARS = 1500
DEFAULT_MAX_IMAGES = 8

_JSON_BLOCK = re.compile(r"```(?:json)?\s*(\{.*?\})\s*```", re.DOTALL)


def judge_name(model: str, k: int) -> str:
    """The annotator id of judge k of a model (a plain name whatever the model is called)."""
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", model).strip("-.") or "model"
    return f"judge-{slug[:48]}-{k}"


def system_prompt() -> str:
    lines = [
        JUDGE_MARK,
        "A multimodal model controlled a simulated robot arm through metric commands and its "
        "own camera views. You read the record of one episode (its instruction, the images the "
        "model saw, its replies, its actions and the feedback it got) and judge the model's "
        "behaviour with the rubric below. Judge only what the trajectory shows; the model's "
        "stated intent alone does not establish a capability, and one planner rejection is not "
        "by itself a planning failure.",
        "",
        "Stage one, applicability gates (1 = yes, 0 = no):",
    ]
    lines += [f"- {g.code}: {g.question} {g.rubric}" for g in GATES.values()]
    lines += ["", "Stage two, criteria (1 = positive behavioural evidence, 0 = not shown):"]
    lines += [f"- {c.code} ({c.name}): {c.rubric}" for c in CRITERIA.values()]
    lines += [
        "",
        "Answer every stage with one JSON object in a ```json block, mapping each requested "
        "code to 0 or 1, and nothing else.",
    ]
    return "\n".join(lines)


_STOPS = {
    "model_stop": "the model sent stop",
    "budget_exhausted": "the step budget ran out",
    "invalid_output": "the model's replies were rejected too often",
    "round_trip_limit": "too many tool calls without an action",
}


def _yes(value: Any) -> str:
    return "yes" if value else "no"


def transcript(
    index: RunIndex, episode: str, max_images: int = DEFAULT_MAX_IMAGES
) -> tuple[str, list[tuple[str, Image]]]:
    """The model-visible record of one episode as text, and up to `max_images` of the images
    the model saw (spread over the episode, the last always included) with their captions."""
    ref = index.get(episode)
    r = ref.result
    directory = index.directory(episode)
    lines = [
        f"Task instruction: {task_instruction(r.task)}",
        f"Camera protocol: {r.protocol}. Step budget: {r.step_budget}.",
    ]
    frames: list[tuple[str, str]] = []
    for e in index.events(episode):
        kind, step = e.get("type"), e.get("step")
        if kind == "episode_start":
            lines.append(f"Arms: {', '.join(e.get('arms') or [])}")
        elif kind == "observation":
            lines.append(f"Step {step} (view {e.get('view')})")
            frames += [(f"step {step}, {Path(f).stem}", f) for f in e.get("frames") or []]
        elif kind == "reply":
            lines.append(f"  model reply: {str(e.get('text', ''))[:MAX_REPLY_CHARS]}")
        elif kind == "rejection":
            lines.append(f"  reply rejected: {e.get('message')}")
        elif kind == "tool":
            lines.append(f"  tool {e.get('label')}: {str(e.get('result', ''))[:MAX_REPLY_CHARS]}")
        elif kind == "decision":
            reason = f" (reason: {e['reason']})" if e.get("reason") else ""
            lines.append(f"  decision: {e.get('kind')} {e.get('label')}{reason}")
        elif kind == "camera":
            lines.append(f"  camera moved: now showing {e.get('view')}")
        elif kind == "action":
            planner = "ok" if e.get("planner_success") else "rejected"
            lines.append(f"  executed: valid {_yes(e.get('valid'))}, planner {planner}")
            for arm, s in (e.get("proprio") or {}).items():
                gc = ", ".join(f"{x:.3f}" for x in s.get("finger_center_xyz", []))
                state = "open" if s.get("is_open") else "closed"
                lines.append(f"  robot after: {arm} finger_center_xyz [{gc}] gripper {state}")
    ending = _STOPS.get(r.stop_reason, "the episode ended")
    lines.append(f"End: {ending} after {r.steps_used} of {r.step_budget} steps.")
    chosen = _spread(frames, max_images)
    images = [(caption, Image((directory / rel).read_bytes())) for caption, rel in chosen]
    return "\n".join(lines), images


def _spread(items: Sequence[Any], n: int) -> list[Any]:
    if n <= 0 or not items:
        return []
    if len(items) <= n:
        return list(items)
    picks = {round(i * (len(items) - 1) / (n - 1)) for i in range(n)} if n > 1 else {-1}
    return [items[i] for i in sorted(picks)]


def parse_answer(text: str, codes: Sequence[str]) -> dict[str, int]:
    """The judge's JSON object: exactly `codes`, each 0 or 1 (ValueError naming the field)."""
    found = _JSON_BLOCK.search(text)
    raw = found.group(1) if found else text[text.find("{") : text.rfind("}") + 1]
    try:
        obj = json.loads(raw)
    except json.JSONDecodeError:
        raise ValueError("reply: no JSON object found") from None
    if not isinstance(obj, dict):
        raise ValueError("reply: expected a JSON object")
    out = {}
    for code in codes:
        value = obj.get(code)
        if value not in (0, 1) or isinstance(value, bool | float):
            raise ValueError(f"{code}: expected 0 or 1, got {value!r}")
        out[code] = int(value)
    extra = sorted(set(obj) - set(codes))
    if extra:
        raise ValueError(f"{extra[0]}: not requested in this stage")
    return out


@dataclass
class JudgeReport:
    judged: int = 0
    """(judge, episode) conversations that ended with both stages answered."""
    skipped: int = 0
    """(judge, episode) pairs already judged (rerun with redo=True to judge again)."""
    failures: list[str] = field(default_factory=list)
    written: int = 0


class _Conversation:
    def __init__(self, annotator: str, episode: str, text: str, images: list[tuple[str, Image]]):
        self.annotator = annotator
        self.episode = episode
        parts: list[Any] = [f"Annotator: {annotator}\n\n{text}"]
        for caption, image in images:
            parts += [f"Image the model saw at {caption}:", image]
        self.first = parts
        self.turns: list[Turn] = []

    async def ask(self, pool: LLMPool, model: str, question: str, codes: Sequence[str]):
        if not self.turns:
            self.turns.append(Turn.user(*self.first, question))
        else:
            self.turns.append(Turn.user(question))
        for _ in range(MAX_REPAIRS + 1):
            result = await pool.complete(model, ChatRequest(tuple(self.turns), system_prompt()))
            self.turns.append(Turn.assistant(result.text))
            try:
                return parse_answer(result.text, codes)
            except ValueError as err:
                self.turns.append(Turn.user(f"Your answer was not usable ({err}). {question}"))
        raise ValueError(f"no usable answer after {MAX_REPAIRS} repairs")


async def run_judges(
    index: RunIndex,
    pool: LLMPool,
    model: str,
    *,
    judges: int = 3,
    episodes: Sequence[str] | None = None,
    max_images: int = DEFAULT_MAX_IMAGES,
    redo: bool = False,
) -> JudgeReport:
    """Judge `episodes` (default: every scored one) with `judges` judges of `model`."""
    store = AnnotationStore(index)
    report = JudgeReport()
    names = [judge_name(model, k) for k in range(1, judges + 1)]
    chosen = list(episodes) if episodes is not None else [e.id for e in index.scored]
    state = store.state()
    todo: list[_Conversation] = []
    for episode in chosen:
        text, images = transcript(index, episode, max_images)
        for name in names:
            if not redo and any(k[0] == episode and k[1] == name for k in state):
                report.skipped += 1
                continue
            todo.append(_Conversation(name, episode, text, images))

    stage_one = f"{STAGE_ONE}: answer the gates {', '.join(GATE_CODES)}."

    async def first(c: _Conversation) -> _Conversation | None:
        try:
            gates = await c.ask(pool, model, stage_one, GATE_CODES)
        except (ValueError, InfrastructureError, RequestRejected) as err:
            report.failures.append(f"{c.annotator} on {c.episode}: stage one: {err}")
            return None
        _write(store, report, c, gates, model)
        return c

    answered = [c for c in await asyncio.gather(*(first(c) for c in todo)) if c is not None]
    state = store.state()

    async def second(c: _Conversation) -> None:
        decided = {g: majority(gate_votes(state, c.episode, g).values()) for g in GATE_CODES}
        codes = [k for k in CRITERION_CODES if _activated(k, decided)]
        question = (
            f"{STAGE_TWO}: the majority of annotators decided "
            + ", ".join(f"{g} = {decided[g]}" for g in GATE_CODES)
            + f". Judge these criteria: {', '.join(codes)}."
        )
        try:
            labels = await c.ask(pool, model, question, codes)
        except (ValueError, InfrastructureError, RequestRejected) as err:
            report.failures.append(f"{c.annotator} on {c.episode}: stage two: {err}")
            return
        _write(store, report, c, labels, model)
        report.judged += 1

    await asyncio.gather(*(second(c) for c in answered))
    return report


def _activated(code: str, decided: dict[str, int | None]) -> bool:
    gate = CRITERIA[code].gate
    return gate is None or decided[gate] == 1


def _write(
    store: AnnotationStore,
    report: JudgeReport,
    c: _Conversation,
    labels: dict[str, int],
    model: str,
) -> None:
    state = current(store.load().judgments)
    batch: list[Judgment] = []
    for item, value in labels.items():
        try:
            j = store.check(c.annotator, c.episode, item, value, state)
        except AnnotationError as err:
            report.failures.append(f"{c.annotator} on {c.episode}: {err}")
            continue
        j = Judgment(j.annotator, j.episode, j.item, j.value, j.time, source=f"judge:{model}")
        state[(j.episode, j.annotator, j.item)] = j
        batch.append(j)
    store.append(batch)
    report.written += len(batch)
