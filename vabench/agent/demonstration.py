"""The demonstration as a model sees it in the learning stage: the frames of the video, the
stage's system prompt and the answers of the three demonstration tools (spec FACTS.md,
"Demonstration protocol"; the session itself is `vabench.agent.learning`).

- `expert.retrieve {}`: the frame index, "frame 0 .. N-1" with the time of each in seconds
  (nothing else: no phase, pose or action).
- `expert.frame {"step": k}` or `{"steps": [k, ...]}` (at most 8): those frames as images.
  A call naming any frame outside 0..N-1 shows none and names the valid range; "view" may be
  omitted or "head" (the video has one camera).
- `expert.learn` is accepted only after `MIN_DISTINCT_FRAMES` distinct frames were shown
  (`gate_message` says why not).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from vabench import protocol as P
from vabench.agent.summary import MAX_LIST_ITEMS, MAX_TEXT_CHARS, DemoSummary
from vabench.agent.tools import ToolResult, tool_text
from vabench.llm_pool.messages import Image

MIN_DISTINCT_FRAMES = 3
"""The learning gate: distinct frames to inspect before `expert.learn` is accepted."""
DEMO_VIEW = "head"
"""The only camera of the demonstration video."""


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
