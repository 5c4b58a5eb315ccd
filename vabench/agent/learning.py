"""The learning session: a model studies one demonstration video through the demonstration
tools and writes the task's summary (spec FACTS.md, "Demonstration protocol"; paper, appendix
"Demonstration-conditioned evaluation protocol").

    result = await learn_summary(task, DemoFrames(jpegs, fps=3.0), llm, "model-a",
                                 recorder=EpisodeRecorder(out_dir))
    if result.summary is not None:
        spec = EpisodeSpec(..., demonstration_summary=summary_text(result.summary))

The session is one conversation (`Conversation`): the learning system prompt
(`learning_prompt`), then the task instruction and the number of frames; then, per model call,
the reply is parsed with `parse_decision` in a context offering only `DEMONSTRATION_TOOLS`
and answered in the same thread:

- `expert.retrieve {}`: the frame index, "frame 0 .. N-1" with the time of each in seconds
  (nothing else: no phase, pose or action).
- `expert.frame {"step": k}` or `{"steps": [k, ...]}` (at most 8): those frames as images.
  A call naming any frame outside 0..N-1 shows none and names the valid range; "view" may be
  omitted or "head" (the video has one camera).
- `expert.learn {"summary": {...}}`: accepted only when (a) at least `MIN_DISTINCT_FRAMES`
  distinct frames have been shown by `expert.frame` (the learning gate; a frame shown twice
  counts once) and (b) `parse_summary` accepts the summary. A refusal lists every reason at
  once (gate and schema) and the session goes on.

Budgets (`LearningLimits`): at most `max_model_calls` model calls in all (30 by default: a
diligent model needs about 3-8; the rest is room for refusals and repairs), and at most
`max_repairs` repair turns in a row for replies that are not a valid decision here (unparsable
JSON, a robot or camera action, stop-less junk), as in the evaluation engine: the third
invalid reply in a row ends the session. A refused `expert.learn` or a bad frame request is a
valid tool call answered with an error: it spends model calls, never repairs. `{"stop": true}`
ends the session without a summary ("model_stop").

Expected failures come back as a `LearningResult` with `status="failed"` and a `stop_reason`;
provider failures that outlast the pool's retries become `status="infrastructure_error"`
(re-run, like evaluation episodes), a request the provider rejects `status="error"`.

No compaction: the call budget bounds the thread (about 30 short turns), and at most
`LearningLimits.context.max_images` images (8) beyond the newest tool result's are sent.

Records, when a recorder is given (events.jsonl of `EpisodeRecorder`): learning_start,
request, reply, rejection, tool, learned, learning_end; and `learning.json` (the
`LearningResult`, summary included) in the recorder's directory. The recorder's `finish` is
not called: it writes an evaluation result; the caller closes the recorder.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field

from vabench import protocol as P
from vabench.agent.conversation import ContextLimits, Conversation
from vabench.agent.records import RECORD_VERSION, EpisodeRecorder, TokenTotals
from vabench.agent.summary import (
    MAX_LIST_ITEMS,
    MAX_TEXT_CHARS,
    DemoSummary,
    parse_summary,
    summary_text,
)
from vabench.agent.tools import ToolResult, tool_text
from vabench.llm_pool.config import GenerationOptions
from vabench.llm_pool.errors import InfrastructureError, RequestRejected
from vabench.llm_pool.messages import Image, Usage
from vabench.llm_pool.pool import LLMPool

MIN_DISTINCT_FRAMES = 3
"""The learning gate: distinct frames to inspect before `expert.learn` is accepted."""
DEMO_VIEW = "head"
"""The only camera of the demonstration video."""

LearningStatus = Literal["learned", "failed", "infrastructure_error", "error"]
StopReason = Literal[
    "learned",
    "budget_exhausted",
    "invalid_output",
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
class DemoFrames:
    """One demonstration video as the model may see it: JPEG frames in order, their rate, and a
    neutral label for the records (never shown to the model; no seed, no file path needed)."""

    frames: Sequence[bytes]
    fps: float
    label: str = "demonstration"
    videos: Sequence[tuple[int, str]] = ()
    """When several videos are shown as one index (the basket task's four atomic videos):
    each video's first frame and its title (the instruction of the skill it shows); frame
    times restart at 0 with each video. Empty: one video."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "frames", tuple(self.frames))
        object.__setattr__(self, "videos", tuple((int(k), str(t)) for k, t in self.videos))
        if not self.frames:
            raise ValueError("frames: a demonstration needs at least one frame")
        starts = [k for k, _ in self.videos]
        if self.videos and (
            starts[0] != 0 or starts != sorted(set(starts)) or starts[-1] >= len(self.frames)
        ):
            raise ValueError(
                f"videos: first frames must start at 0, increase and lie in the video, got {starts}"
            )
        bad = [i for i, f in enumerate(self.frames) if not isinstance(f, bytes) or not f]
        if bad:
            raise ValueError(f"frames[{bad[0]}]: expected non-empty JPEG bytes")
        if not (isinstance(self.fps, int | float) and math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps: expected a positive number, got {self.fps!r}")

    def __len__(self) -> int:
        return len(self.frames)

    def locate(self, k: int) -> tuple[int, float]:
        """Frame `k`'s video (1-based; 1 when there is one) and its time in that video (s)."""
        start, video = 0, 1
        for j, (first, _) in enumerate(self.videos, start=1):
            if first <= k:
                start, video = first, j
        return video, round((k - start) / self.fps, 2)

    def index_entry(self, k: int) -> dict[str, Any]:
        video, t = self.locate(k)
        return {"frame": k, "video": video, "t_s": t} if self.videos else {"frame": k, "t_s": t}

    @classmethod
    def concat(cls, parts: Sequence[tuple[str, DemoFrames]], label: str) -> DemoFrames:
        """Several videos (title, frames) as one index; all must share one frame rate."""
        if not parts:
            raise ValueError("parts: at least one video")
        fps = parts[0][1].fps
        if any(d.fps != fps for _, d in parts):
            raise ValueError(f"parts: videos of different frame rates {[d.fps for _, d in parts]}")
        frames: list[bytes] = []
        videos = []
        for title, demo in parts:
            videos.append((len(frames), title))
            frames += demo.frames
        return cls(frames, fps, label, videos)


@dataclass(frozen=True)
class LearningLimits:
    """The budgets of one session (module docstring) and its context bounds."""

    max_model_calls: int = 30
    max_repairs: int = P.MAX_REPAIRS_PER_DECISION
    context: ContextLimits = field(default_factory=lambda: ContextLimits(max_images=8))
    """Up to 8 older frames stay visible, so that a model can compare what it inspected."""
    generation: GenerationOptions | None = None

    def __post_init__(self) -> None:
        if self.max_model_calls < 1:
            raise ValueError(f"max_model_calls must be >= 1, got {self.max_model_calls}")
        if self.max_repairs < 0:
            raise ValueError(f"max_repairs must be >= 0, got {self.max_repairs}")


class LearningResult(BaseModel):
    """How one learning session ended (written as learning.json)."""

    model_config = ConfigDict(extra="forbid")
    v: int = RECORD_VERSION
    task: str
    model: str
    label: str
    status: LearningStatus
    stop_reason: StopReason
    error: str | None = None
    summary: DemoSummary | None = None
    summary_text: str | None = None
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

    @property
    def learned(self) -> bool:
        return self.summary is not None


# -- prompt ------------------------------------------------------------------------------------


def _field_lines(required: bool) -> list[str]:
    return [
        f"  - {name}: {f.description}"
        for name, f in DemoSummary.model_fields.items()
        if f.is_required() == required
    ]


def learning_prompt(arms: Sequence[str], fps: float, n_videos: int = 1) -> str:
    """The system prompt of the learning stage (the field list comes from `DemoSummary`);
    `n_videos` > 1: the videos show the skills the task combines (the basket task)."""
    robot = "two robot arms (left and right)" if len(arms) > 1 else "one robot arm"
    what = (
        "an RGB video from the robot's head camera of a successful execution of the same task"
        if n_videos == 1
        else f"{n_videos} RGB videos from the robot's head camera, each a successful execution "
        "of one skill that the task combines, shown as one numbered list of frames"
    )
    return "\n".join(
        [
            f"You will control {robot} with parallel-jaw grippers at a table, in simulation. "
            f"Before that, in this stage, you study a demonstration: {what}, sampled at about "
            f"{fps:g} frames per second. It contains images only: no positions, joint values, "
            "actions, contacts or phases.",
            "",
            "Your goal is a structured summary of how the task was done, which you will read "
            "at every decision later, in new scenes of the same task where the objects lie "
            "elsewhere. Describe what to do and what to check, not the positions seen here.",
            "",
            "# Tools (one per reply)",
            '- {"tool": "expert.retrieve", "args": {}}: lists the frames, "frame 0" to '
            '"frame N-1", with the time of each in seconds.',
            '- {"tool": "expert.frame", "args": {"step": k}} or {"steps": [k1, k2, ...]}: '
            f"shows those frames (at most {P.MAX_EXPERT_FRAMES} per call).",
            '- {"tool": "expert.learn", "args": {"summary": {...}}}: stores your summary and '
            "ends this stage. It is accepted only after you have inspected at least "
            f"{MIN_DISTINCT_FRAMES} distinct frames with expert.frame.",
            P.LEARNING_STAGE_MARK,
            "",
            "# Summary fields",
            "A JSON object; strings unless said otherwise. The optional fields that describe "
            "several things (stages, constraints, roles, sequences, notes) also take a list of "
            f"strings. At most {MAX_TEXT_CHARS} characters per string and {MAX_LIST_ITEMS} "
            "items per list.",
            "Required:",
            *_field_lines(required=True),
            "Optional:",
            *_field_lines(required=False),
            "",
            "# Reply format",
            "Reply with exactly one JSON object per reply, in a ```json block, for example:",
            '```json\n{"tool": "expert.frame", "args": {"steps": [0, 5, 10]}}\n```',
        ]
    )


def first_turn(instruction: str, demo: DemoFrames) -> str:
    """The first user turn: the task and the size of the video (and its parts, if several)."""
    n = len(demo)
    lines = [f"Task instruction: {instruction}"]
    if not demo.videos:
        lines.append(f"The demonstration video has {n} frames (frame 0 to frame {n - 1}).")
    else:
        lines.append(f"The demonstration has {len(demo.videos)} videos, {n} frames in all:")
        ends = [k for k, _ in demo.videos[1:]] + [n]
        for j, ((first, title), end) in enumerate(zip(demo.videos, ends, strict=True), start=1):
            lines.append(f"- video {j}, frames {first} to {end - 1}: {title}")
    lines.append("Inspect it with the tools, then submit your summary with expert.learn.")
    return "\n".join(lines)


# -- tools --------------------------------------------------------------------------------------


def retrieve_result(demo: DemoFrames) -> ToolResult:
    """`expert.retrieve`: the ordered frame index with times (s), nothing else."""
    index = [demo.index_entry(k) for k in range(len(demo))]
    name = "expert.retrieve"
    return ToolResult(name, tool_text(name, {"n_frames": len(demo), "frames": index}))


def frame_result(demo: DemoFrames, args: P.FrameArgs) -> ToolResult:
    """`expert.frame`: the requested frames as images, or an error naming the valid range."""
    name = "expert.frame"
    n = len(demo)
    if args.view is not None and args.view != DEMO_VIEW:
        error = f"args.view: the demonstration has one view, {DEMO_VIEW!r}; omit 'view'"
        return ToolResult(name, tool_text(name, {"error": error}), ok=False)
    wanted = args.frames
    outside = [k for k in wanted if not 0 <= k < n]
    if outside:
        where = "args.step" if args.step is not None else "args.steps"
        error = (
            f"{where}: no frame {', '.join(map(str, outside))}; valid frames: 0 to {n - 1}"
            "; no frame was shown"
        )
        return ToolResult(name, tool_text(name, {"error": error}), ok=False)
    payload = {
        "frames": [demo.index_entry(k) for k in wanted],
        "result": "the frames follow, in this order",
    }
    images = tuple(Image(demo.frames[k]) for k in wanted)
    return ToolResult(name, tool_text(name, payload), images)


def gate_message(inspected: Sequence[int]) -> str:
    """Why `expert.learn` is refused while fewer than `MIN_DISTINCT_FRAMES` were inspected."""
    seen = ", ".join(map(str, sorted(inspected))) or "none"
    return (
        f"learning gate: inspect at least {MIN_DISTINCT_FRAMES} distinct demonstration frames "
        f"with expert.frame before expert.learn; distinct frames inspected so far: "
        f"{len(inspected)} ({seen})"
    )


# -- the session ----------------------------------------------------------------------------------


class _End(Exception):
    def __init__(self, status: LearningStatus, reason: StopReason, error: str | None = None):
        super().__init__(reason)
        self.status, self.reason, self.error = status, reason, error


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
    summary: DemoSummary | None = None
    calls: int = 0
    tools: int = 0
    invalid: int = 0
    refusals: int = 0
    usage: Usage = field(default_factory=Usage)
    cost: float = 0.0

    def __post_init__(self) -> None:
        arms = tuple(self.task.arms)
        self.conv = Conversation(
            learning_prompt(arms, self.demo.fps, max(1, len(self.demo.videos))),
            "active",
            limits=self.limits.context,
        )
        self.ctx = P.DecisionContext(arms, "active", P.DEMONSTRATION_TOOLS)

    def event(self, type_: str, **fields: Any) -> None:
        if self.rec is not None:
            self.rec.event(type_, **fields)

    async def run(self) -> None:
        self.conv.add_note(first_turn(self.task.instruction, self.demo))
        repairs = 0
        while self.calls < self.limits.max_model_calls:
            reply = await self._call()
            try:
                decision = P.parse_decision(reply, self.ctx)
                if isinstance(decision, P.Stop):
                    raise _End("failed", "model_stop", "the model stopped without a summary")
                if not isinstance(decision, P.ToolCall):
                    raise P.DecisionError(
                        "action",
                        "no actions in the learning stage (no robot or camera actions); "
                        "use expert.retrieve, expert.frame or expert.learn",
                    )
            except P.DecisionError as err:
                self.invalid += 1
                self.event("rejection", call=self.calls, field=err.field, message=str(err))
                if repairs >= self.limits.max_repairs:
                    raise _End("failed", "invalid_output", str(err)) from None
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
        raise _End(
            "failed",
            "budget_exhausted",
            f"{self.limits.max_model_calls} model calls without an accepted summary",
        )

    async def _call(self) -> str:
        request = self.conv.request(self.limits.generation)
        self.event(
            "request", call=self.calls + 1, turns=len(request.turns), images=len(request.images)
        )
        result = await self.llm.complete(self.model, request)
        self.calls += 1
        self.usage = self.usage + result.usage
        self.cost += result.cost_usd
        self.conv.add_reply(result.text)
        self.event(
            "reply",
            call=self.calls,
            text=result.text,
            finish_reason=result.finish_reason,
            latency_s=round(result.latency_s, 4),
            attempts=result.attempts,
            usage=dataclasses.asdict(result.usage),
            cost_usd=result.cost_usd,
        )
        return result.text

    def _tool(self, call: P.ToolCall) -> None:
        self.tools += 1
        if call.name == "expert.retrieve":
            result = retrieve_result(self.demo)
        elif call.name == "expert.frame":
            assert isinstance(call.args, P.FrameArgs)
            result = frame_result(self.demo, call.args)
            if result.ok:
                self.inspected.update(dict.fromkeys(call.args.frames))
        else:
            assert isinstance(call.args, P.LearnArgs)
            result = self._learn(call.args.summary)
        names = [f"demonstration frame {k}" for k in getattr(call.args, "frames", ())]
        self.event(
            "tool",
            call=self.calls,
            label=P.decision_label(call),
            ok=result.ok,
            result=result.text,
            images=len(result.images),
            distinct_frames=len(self.inspected),
        )
        self.conv.add_tool_result(result.text, result.images, image_names=names)

    def _learn(self, raw: str | dict[str, Any]) -> ToolResult:
        name = "expert.learn"
        problems: list[str] = []
        if len(self.inspected) < MIN_DISTINCT_FRAMES:
            problems.append(gate_message(list(self.inspected)))
        summary = None
        try:
            summary = parse_summary(raw)
        except P.DecisionError as err:
            problems.append(str(err))
        if problems:
            self.refusals += 1
            error = "summary not accepted: " + "; ".join(problems)
            return ToolResult(name, tool_text(name, {"error": error}), ok=False)
        assert summary is not None
        self.summary = summary
        self.event("learned", call=self.calls, summary=summary.model_dump(exclude_none=True))
        return ToolResult(name, tool_text(name, {"result": "summary stored"}))


async def learn_summary(
    task: LearningTask,
    frames: DemoFrames,
    llm: LLMPool,
    model: str,
    *,
    recorder: EpisodeRecorder | None = None,
    limits: LearningLimits | None = None,
) -> LearningResult:
    """One learning session of `model` on `task`'s demonstration `frames` (module docstring).

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
        max_model_calls=limits.max_model_calls,
        max_repairs=limits.max_repairs,
    )
    status: LearningStatus = "learned"
    reason: StopReason = "learned"
    error: str | None = None
    try:
        await session.run()
    except _End as end:
        status, reason, error = end.status, end.reason, end.error
    except InfrastructureError as err:
        status, reason, error = "infrastructure_error", "infrastructure_error", str(err)
    except RequestRejected as err:
        if err.fatal:  # the endpoint refuses every request: nothing to store, the sweep stops
            session.event("endpoint_refused", status=err.status, error=str(err))
            raise
        status, reason, error = "error", "request_rejected", f"{err.status}: {err}"
    s, u = session.summary, session.usage
    result = LearningResult(
        task=task.name,
        model=model,
        label=frames.label,
        status=status,
        stop_reason=reason,
        error=error,
        summary=s,
        summary_text=summary_text(s) if s is not None else None,
        n_frames=len(frames),
        frames_inspected=list(session.inspected),
        model_calls=session.calls,
        tool_calls=session.tools,
        invalid_outputs=session.invalid,
        learn_refusals=session.refusals,
        tokens=TokenTotals(
            input=u.input_tokens,
            cached_input=u.cached_input_tokens,
            cache_write=u.cache_write_tokens,
            output=u.output_tokens,
            reasoning=u.reasoning_tokens or 0,
        ),
        cost_usd=round(session.cost, 6),
        wall_s=round(time.time() - t0, 3),
    )
    session.event("learning_end", status=status, stop_reason=reason, error=error)
    if recorder is not None and recorder.directory is not None:
        write_result(recorder.directory / "learning.json", result)
    return result


def write_result(path: os.PathLike[str] | str, result: LearningResult) -> None:
    """Write `result` as JSON, atomically (a reader never sees half a file)."""
    tmp = f"{os.fspath(path)}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(result.model_dump_json(indent=1, exclude_none=False))
    os.replace(tmp, path)


def read_result(path: os.PathLike[str] | str) -> LearningResult:
    """A `learning.json` written by `write_result`."""
    with open(path, encoding="utf-8") as f:
        return LearningResult.model_validate(json.load(f))
