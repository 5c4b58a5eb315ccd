"""The learning session: a model studies one demonstration through the demonstration tools
and writes the task's summary (spec PROTOCOL_FACTS.md 6; paper, appendix
"Demonstration-conditioned evaluation protocol").

    result = await learn_summary(task, DemoFrames(jpegs, fps=3.0, scene=scene), llm, "model-a",
                                 recorder=EpisodeRecorder(out_dir))
    if result.summary_text is not None:
        spec = EpisodeSpec(..., demonstration_summary=result.summary_text)

The session is one conversation (`Conversation`): the learning system prompt
(`learning_prompt`), then the first message (`first_turn`: the scene the video starts from,
its observation text and head-camera image, or for the basket's atomic videos the task and
the list of videos); then, per model call, the reply is parsed with `parse_decision` in a
context offering only `DEMONSTRATION_TOOLS` and answered in the same thread:

- `expert.retrieve` and `expert.frame`: answered by `vabench.agent.demonstration` (the frame
  index with times; the frames asked for, or an error naming the valid range).
- `expert.learn {...the summary fields...}`: accepted only when (a) the learning gate is
  passed (`gate_problems`: expert.retrieve called, at least `MIN_DISTINCT_FRAMES` distinct
  frames shown, of every video when there are several; a frame shown twice counts once) and
  (b) `parse_summary` accepts the fields. A refusal lists every reason at once (gate and
  fields) as the tool's error and the session goes on.

Budgets (`LearningLimits`): at most `max_model_calls` model calls in all (20 by default, the
reference's one learning decision: a diligent model needs about 3-8), and at most
`max_repairs` repair turns in a row for replies that are not a valid decision here (unparsable
JSON, a robot or camera action, stop-less junk), as in the evaluation engine: the third
invalid reply in a row ends the session. A refused `expert.learn` or a bad frame request is a
valid tool call answered with an error: it spends model calls, never repairs. `{"stop": true}`
ends the session without a summary ("model_stop").

Replies are read as in evaluation episodes (`vabench.agent.replies`): a refusal, a reply cut
at the output limit, an empty or reasoning-only reply each get a repair that says so, and
repairs that run out end the session `refused`, `truncated` or `invalid_output`; a request
beyond the model's context window ends it `context_exceeded` (the session does not compact).

Expected failures come back as a `LearningResult` with `status="failed"` and a `stop_reason`
(the sweep runs such a session again, up to three attempts: `vabench.agent.learning_stage`);
provider failures that outlast the pool's retries become `status="infrastructure_error"`
(re-run, like evaluation episodes), a request the provider rejects `status="error"`.

No compaction: the call budget bounds the thread (about 40 short turns), and at most
`LearningLimits.context.max_images` images (8) beyond the newest tool result's are sent.

Records, when a recorder is given (events.jsonl of `EpisodeRecorder`): learning_start,
request, reply, rejection, tool, learned, learning_end; and `learning.json` (the
`LearningResult`, summary included, `LEARNING_VERSION`) in the recorder's directory. The
recorder's `finish` is not called: it writes an evaluation result; the caller closes the
recorder.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from vabench import protocol as P
from vabench.agent.conversation import ContextLimits, Conversation
from vabench.agent.demonstration import (
    SCENE_IMAGE_NAME,
    DemoFrames,
    first_turn,
    frame_result,
    gate_problems,
    learning_prompt,
    retrieve_result,
)
from vabench.agent.records import EpisodeRecorder, TokenTotals
from vabench.agent.replies import ReplyRejected, history_text, read_decision, stop_reason_of
from vabench.agent.session import SessionEnd, Spend, reply_fields
from vabench.agent.summary import parse_summary, summary_text
from vabench.agent.tools import ToolResult, tool_text
from vabench.llm_pool.config import GenerationOptions
from vabench.llm_pool.errors import InfrastructureError, RequestRejected
from vabench.llm_pool.messages import CompletionResult
from vabench.llm_pool.pool import LLMPool
from vabench.run_layout import EpisodeDir

LearningStatus = Literal["learned", "failed", "infrastructure_error", "error"]
StopReason = Literal[
    "learned",
    "budget_exhausted",
    "invalid_output",
    "refused",
    "truncated",
    "context_exceeded",
    "model_stop",
    "infrastructure_error",
    "request_rejected",
]


class LearningTask(Protocol):
    """What the session needs of a task (`vabench.tasks.base.Task` has it)."""

    @property
    def name(self) -> str: ...
    @property
    def instruction(self) -> str: ...
    @property
    def arms(self) -> tuple[str, ...]: ...


@dataclass(frozen=True)
class LearningLimits:
    """The budgets of one session (module docstring) and its context bounds."""

    max_model_calls: int = 20
    max_repairs: int = P.MAX_REPAIRS_PER_DECISION
    context: ContextLimits = field(default_factory=lambda: ContextLimits(max_images=8))
    """Up to 8 older frames stay visible, so that a model can compare what it inspected."""
    generation: GenerationOptions | None = None

    def __post_init__(self) -> None:
        if self.max_model_calls < 1:
            raise ValueError(f"max_model_calls must be >= 1, got {self.max_model_calls}")
        if self.max_repairs < 0:
            raise ValueError(f"max_repairs must be >= 0, got {self.max_repairs}")


LEARNING_VERSION = 2
"""The version of `LearningResult` records. 1: the summary under a fixed schema with length
limits, shown as "- field: value" lines, one attempt; 2: the summary as the model's fields,
shown as JSON, the scene flag and the attempts. Version 1 records still read."""
READABLE_VERSIONS = (1, LEARNING_VERSION)


class LearningResult(BaseModel):
    """How one learning session ended (written as learning.json), or, as the sweep stores it
    per (model, family), how the last of its attempts ended with the earlier ones inside."""

    model_config = ConfigDict(extra="forbid")
    v: int = LEARNING_VERSION
    task: str
    model: str
    label: str
    status: LearningStatus
    stop_reason: StopReason
    error: str | None = None
    summary: dict[str, Any] | None = None
    """The accepted summary's fields, as the model wrote them (`agent.summary`)."""
    summary_text: str | None = None
    """The summary as every observation of the evaluation shows it."""
    scene: bool = False
    """Whether the first message showed the scene the video starts from."""
    n_frames: int
    frames_inspected: list[int] = Field(default_factory=list)
    """Distinct frames shown, in the order first shown."""
    model_calls: int = 0
    tool_calls: int = 0
    invalid_outputs: int = 0
    learn_refusals: int = 0
    tokens: TokenTotals = Field(default_factory=TokenTotals)
    cost_usd: float = 0.0
    wall_s: float = 0.0
    attempt: int = Field(default=1, ge=1)
    """Which attempt of the sweep's learning stage this session was (1-based)."""
    earlier_attempts: list[LearningResult] = Field(default_factory=list)
    """The sweep's earlier attempts of the same (model, family), each failed, in order (their
    calls were billed too); empty in a session's own learning.json."""

    @model_validator(mode="before")
    @classmethod
    def _upgrade(cls, data: Any) -> Any:
        # A version-1 record wrote every optional summary field, null when unset.
        if isinstance(data, dict) and data.get("v") == 1:
            data = {**data, "v": LEARNING_VERSION}
            if isinstance(data.get("summary"), dict):
                data["summary"] = {k: v for k, v in data["summary"].items() if v is not None}
        return data

    @field_validator("v")
    @classmethod
    def _readable(cls, v: int) -> int:
        if v not in READABLE_VERSIONS:
            raise ValueError(
                f"a learning record of version {v}; this vabench reads versions "
                f"{', '.join(map(str, READABLE_VERSIONS))}: read it with the vabench that wrote "
                "it, or remove it to learn the summary again"
            )
        return v

    @property
    def learned(self) -> bool:
        return self.summary is not None


# -- the session ----------------------------------------------------------------------------------


@dataclass
class _Session:
    task: LearningTask
    demo: DemoFrames
    llm: LLMPool
    model: str
    limits: LearningLimits
    rec: EpisodeRecorder | None
    conv: Conversation = field(init=False)
    ctx: P.DecisionContext = field(init=False)
    inspected: dict[int, None] = field(default_factory=dict)  # ordered set
    retrieved: bool = False
    summary: dict[str, Any] | None = None
    tools: int = 0
    invalid: int = 0
    refusals: int = 0
    spend: Spend = field(default_factory=Spend)

    def __post_init__(self) -> None:
        arms = tuple(self.task.arms)
        self.conv = Conversation(
            learning_prompt(
                arms,
                self.demo.fps,
                max(1, len(self.demo.videos)),
                scene=self.demo.scene is not None,
            ),
            "active",
            limits=self.limits.context,
        )
        self.ctx = P.DecisionContext(arms, "active", P.DEMONSTRATION_TOOLS)

    def event(self, type_: str, **fields: Any) -> None:
        if self.rec is not None:
            self.rec.event(type_, **fields)

    async def run(self) -> None:
        text, images = first_turn(self.task.instruction, self.demo)
        if images:  # a named image, so that its placeholder says which it was once dropped
            self.conv.add_tool_result(text, images, image_names=(SCENE_IMAGE_NAME,))
        else:
            self.conv.add_note(text)
        repairs = 0
        while self.spend.calls < self.limits.max_model_calls:
            reply = await self._call()
            try:
                decision = read_decision(reply, self.ctx, self._output_limit())
                if isinstance(decision, P.Stop):
                    raise SessionEnd("failed", "model_stop", "the model stopped without a summary")
                if not isinstance(decision, P.ToolCall):
                    raise ReplyRejected(
                        "invalid",
                        "action",
                        "no actions in the learning stage (no robot or camera actions); "
                        "use expert.retrieve, expert.frame or expert.learn",
                    )
            except ReplyRejected as err:
                self.invalid += 1
                self.event(
                    "rejection",
                    call=self.spend.calls,
                    kind=err.kind,
                    field=err.field,
                    message=str(err),
                )
                if repairs >= self.limits.max_repairs:
                    raise SessionEnd("failed", stop_reason_of(err.kind), str(err)) from None
                repairs += 1
                self.conv.add_note(
                    f"Your previous reply was not accepted: {err}\n"
                    "Reply again with one JSON object: a demonstration tool call."
                )
                continue
            repairs = 0
            self._tool(decision)
            if self.summary is not None:
                return
        raise SessionEnd(
            "failed",
            "budget_exhausted",
            f"{self.limits.max_model_calls} model calls without an accepted summary",
        )

    def _output_limit(self) -> int:
        endpoint = self.llm.endpoint(self.model).config
        return endpoint.generation.merge(self.limits.generation).resolved_max_output_tokens

    async def _call(self) -> CompletionResult:
        request = self.conv.request(self.limits.generation)
        self.event(
            "request",
            call=self.spend.calls + 1,
            turns=len(request.turns),
            images=len(request.images),
        )
        result = await self.llm.complete(self.model, request)
        self.spend.add(result)
        self.conv.add_reply(history_text(result))
        self.event(
            "reply",
            call=self.spend.calls,
            **reply_fields(result),
            reasoning=result.reasoning,
            raw_finish_reason=result.raw_finish_reason,
        )
        return result

    def _tool(self, call: P.ToolCall) -> None:
        self.tools += 1
        if call.name == "expert.retrieve":
            result = retrieve_result(self.demo)
            self.retrieved = True
        elif call.name == "expert.frame":
            assert isinstance(call.args, P.FrameArgs)
            result = frame_result(self.demo, call.args)
            if result.ok:
                self.inspected.update(dict.fromkeys(call.args.frames))
        else:
            assert isinstance(call.args, P.LearnArgs)
            result = self._learn(call.args.fields)
        names = [f"demonstration frame {k}" for k in getattr(call.args, "frames", ())]
        self.event(
            "tool",
            call=self.spend.calls,
            label=P.decision_label(call),
            ok=result.ok,
            result=result.text,
            images=len(result.images),
            distinct_frames=len(self.inspected),
        )
        self.conv.add_tool_result(result.text, result.images, image_names=names)

    def _learn(self, fields: dict[str, Any]) -> ToolResult:
        name = "expert.learn"
        problems = gate_problems(self.demo, self.retrieved, list(self.inspected))
        summary = None
        try:
            summary = parse_summary(fields, composite=self.demo.composite)
        except P.DecisionError as err:
            problems.append(str(err))
        if problems:
            self.refusals += 1
            error = "summary not accepted: " + "; ".join(problems)
            return ToolResult(name, tool_text(name, {"error": error}), ok=False)
        assert summary is not None
        self.summary = summary
        self.event("learned", call=self.spend.calls, summary=summary)
        return ToolResult(name, tool_text(name, {"result": "summary stored"}))


async def learn_summary(
    task: LearningTask,
    frames: DemoFrames,
    llm: LLMPool,
    model: str,
    *,
    recorder: EpisodeRecorder | None = None,
    limits: LearningLimits | None = None,
    attempt: int = 1,
) -> LearningResult:
    """One learning session of `model` on `task`'s demonstration `frames` (module docstring);
    `attempt`: which of the sweep's attempts it is, for the records.

    Returns a `LearningResult` in every case but a harness bug: `summary` set when learned."""
    limits = limits or LearningLimits()
    session = _Session(task, frames, llm, model, limits, recorder)
    t0 = time.time()
    session.event(
        "learning_start",
        task=task.name,
        model=model,
        label=frames.label,
        n_frames=len(frames),
        fps=frames.fps,
        scene=frames.scene is not None,
        max_model_calls=limits.max_model_calls,
        max_repairs=limits.max_repairs,
        attempt=attempt,
    )
    status: LearningStatus = "learned"
    reason: StopReason = "learned"
    error: str | None = None
    try:
        await session.run()
    except SessionEnd as end:
        status, reason, error = end.status, end.reason, end.error  # type: ignore[assignment]
    except InfrastructureError as err:
        status, reason, error = "infrastructure_error", "infrastructure_error", str(err)
    except RequestRejected as err:
        if err.fatal:  # the endpoint refuses every request: nothing to store, the sweep stops
            session.event("endpoint_refused", status=err.status, error=str(err))
            raise
        if err.context_exceeded:  # no compaction here: the model's own failure, as in episodes
            status, reason, error = "failed", "context_exceeded", str(err)
        else:
            status, reason, error = "error", "request_rejected", f"{err.status}: {err}"
    s = session.summary
    result = LearningResult(
        task=task.name,
        model=model,
        label=frames.label,
        status=status,
        stop_reason=reason,
        error=error,
        summary=s,
        summary_text=summary_text(s) if s is not None else None,
        scene=frames.scene is not None,
        n_frames=len(frames),
        frames_inspected=list(session.inspected),
        model_calls=session.spend.calls,
        tool_calls=session.tools,
        invalid_outputs=session.invalid,
        learn_refusals=session.refusals,
        tokens=session.spend.tokens(),
        cost_usd=round(session.spend.cost, 6),
        wall_s=round(time.time() - t0, 3),
        attempt=attempt,
    )
    session.event("learning_end", status=status, stop_reason=reason, error=error)
    if recorder is not None and recorder.directory is not None:
        write_result(EpisodeDir(recorder.directory).learning_result, result)
    return result


def write_result(path: os.PathLike[str] | str, result: LearningResult) -> None:
    """Write `result` as JSON, atomically (a reader never sees half a file)."""
    tmp = f"{os.fspath(path)}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(result.model_dump_json(indent=1, exclude_none=False))
    os.replace(tmp, path)


def read_result(path: os.PathLike[str] | str) -> LearningResult:
    """A `learning.json` written by `write_result` (of any of `READABLE_VERSIONS`); raises
    `json.JSONDecodeError` or pydantic's `ValidationError` (an unreadable version: field
    "v") otherwise."""
    with open(path, encoding="utf-8") as f:
        return LearningResult.model_validate(json.load(f))
