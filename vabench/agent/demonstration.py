"""The demonstration as a model sees it in the learning stage: the frames of the video, the
scene it starts from, the stage's system prompt and first message, and the answers of the
three demonstration tools (spec PROTOCOL_FACTS.md 6.1-6.3; the session itself is
`vabench.agent.learning`).

- The first message: the scene at the start of the demonstration as an evaluation episode's
  first observation shows it (`scene_observation`: the same text, from the robot state the
  model may see, and the head-camera image, which is frame 0 of the video), then the size of
  the video. The basket's atomic videos come without a scene (they show single skills, not
  the task): the message says so and lists the videos.
- `expert.retrieve {}`: the frame index, "frame 0 .. N-1" with the time of each in seconds
  (and its video, when there are several); nothing else: no phase, pose or action.
- `expert.frame {"step": k}` or `{"steps": [k, ...]}` (at most 8): those frames as images.
  A call naming any frame outside 0..N-1 shows none and names the valid range; "view" may be
  omitted or "head" (the video has one camera).
- `expert.learn` is accepted only after `expert.retrieve` and `MIN_DISTINCT_FRAMES` distinct
  frames shown, of every video when there are several (`gate_problems` says what is missing).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from vabench import protocol as P
from vabench.agent.observation import ActionFeedback, observation_text
from vabench.agent.summary import (
    AFFORDANCE_ENUMS,
    AFFORDANCE_FLAGS,
    CHECKED_FIELDS,
    FREE_FIELDS,
    REQUIRED_FIELDS,
)
from vabench.agent.tools import ToolResult, tool_text
from vabench.llm_pool.messages import Image

MIN_DISTINCT_FRAMES = 3
"""The learning gate: distinct frames to inspect (of each video) before `expert.learn`."""
DEMO_VIEW = "head"
"""The only camera of the demonstration video."""
SCENE_IMAGE_NAME = "the scene's head-camera image"
"""The placeholder name of the first message's image once it ages out of the requests."""


@dataclass(frozen=True)
class DemoScene:
    """The scene a demonstration starts from, as the model may see it: an evaluation episode's
    first observation text at the demonstration's seed (`scene_observation`) and its
    head-camera image (JPEG: frame 0 of the video)."""

    text: str
    image: bytes

    def __post_init__(self) -> None:
        if not self.text.strip():
            raise ValueError("text: the scene's observation text is empty")
        if not isinstance(self.image, bytes) or not self.image:
            raise ValueError("image: expected non-empty JPEG bytes")


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
    scene: DemoScene | None = None
    """The scene the video starts from (one video only); None: no scene is shown."""

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
        if self.scene is not None and self.composite:
            raise ValueError("scene: several videos show no one scene")

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def composite(self) -> bool:
        """Several videos of single skills (the basket's form)."""
        return len(self.videos) > 1

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


def scene_observation(
    instruction: str, arms: Sequence[str], robot: Mapping[str, Mapping[str, Any]]
) -> str:
    """The text of an active evaluation episode's first observation in a scene whose robot
    state is `robot` (`sim_mjx.layout.proprio_fields` of the reset; filtered as every
    observation's): what the engine shows at step 1, with no summary (none is learned yet)."""
    tools = P.available_tools(demonstration=False)
    return observation_text(
        step=1,
        step_budget=1,  # never shown
        instruction=instruction,
        proprio=robot,
        arms=tuple(arms),
        feedback=ActionFeedback(),
        executed_actions=[],
        demonstration_summary=None,
        available_actions=P.available_actions(tuple(arms), "active", tools),
        history_steps=[],
    )


# -- prompt ------------------------------------------------------------------------------------


def _fields(fields: Mapping[str, str]) -> list[str]:
    return [f"  - {name}: {what}" for name, what in fields.items()]


def _profile_lines() -> list[str]:
    enums = [f"{name} (one of {', '.join(values)})" for name, values in AFFORDANCE_ENUMS.items()]
    return ["    " + "; ".join(enums) + "; and the booleans " + ", ".join(AFFORDANCE_FLAGS) + "."]


def learning_prompt(
    arms: Sequence[str], fps: float, n_videos: int = 1, *, scene: bool = False
) -> str:
    """The system prompt of the learning stage. `n_videos` > 1: the videos show the single
    skills the task combines (the basket task); `scene`: the first message shows the scene
    the video starts from."""
    dual = len(arms) > 1
    robot = "two robot arms (left and right)" if dual else "one robot arm"
    composite = n_videos > 1
    what = (
        f"{n_videos} RGB videos from the robot's head camera, each a successful execution of "
        "one skill that the task combines, shown as one numbered list of frames"
        if composite
        else "an RGB video from the robot's head camera of a successful execution of the same task"
    )
    lines = [
        f"You will control {robot} with parallel-jaw grippers at a table, in simulation. "
        f"Before that, in this stage, you study a demonstration: {what}, sampled at about "
        f"{fps:g} frames per second. "
        + ("The videos are" if composite else "The video is")
        + " images only: no end-effector poses, joint values, gripper values, actions, "
        "coordinates, contacts or phases come with " + ("them." if composite else "it."),
        "",
        "Your goal is a structured summary of how the task was done, which you will read "
        "at every decision later, in new scenes of the same task where the objects lie "
        "elsewhere. Describe what to do and what to check; do not invent metric "
        "coordinates.",
    ]
    if scene:
        lines += [
            "",
            "Your first message shows the scene the video starts from, as an observation of "
            "the evaluation presents it: its text, then the head-camera image (the moment of "
            "frame 0). The actions it lists are the evaluation's; none of them can be used in "
            "this stage.",
        ]
    if composite:
        lines += [
            "",
            "The videos show single skills, not this task in one run, and no scene of the "
            "task is shown: learn skills that transfer per object type. Which objects an "
            "episode holds, how many of each, where and in what order are for each episode "
            "to show.",
        ]
    per = " of every video" if composite else ""
    span = (
        "its start, the grasp or the closing of the fingers, and its end"
        if composite
        else "the early part, the middle, the grasp (fingers closing) and the lift"
    )
    lines += [
        "",
        "# Steps",
        '1. {"tool": "expert.retrieve", "args": {}} first: it lists the frames, "frame 0" to '
        '"frame N-1", with the time of each in seconds'
        + (" and the video it belongs to." if composite else "."),
        '2. {"tool": "expert.frame", "args": {"step": k}} or {"steps": [k1, k2, ...]} shows '
        f"those frames (at most {P.MAX_EXPERT_FRAMES} per call). Choose them yourself"
        + (", studying every video separately," if composite else "")
        + f" to cover {span}.",
        '3. {"tool": "expert.learn", "args": {"grasp_object_part": "...", "grasp_region": '
        '"...", ..., "pre_close_checks": ["..."], "test_lift_rule": "..."}} stores the '
        "summary, its fields directly in args, and ends this stage. It is refused until "
        f"expert.retrieve was called and at least {MIN_DISTINCT_FRAMES} distinct frames{per} "
        "were shown with expert.frame.",
        "One tool call per reply. " + P.LEARNING_STAGE_MARK,
        "",
        "# The summary",
        "Name what the video shows: where the object was grasped and which part, the regions "
        "avoided, the approach, the posture, where the fingers sat, the task stage, the goal "
        "after the grasp and the constraints the object's function sets.",
    ]
    if dual:
        lines.append(
            "With two arms, also which arm does what, the phases in order, the moves the arms "
            "make together and the rule for releasing or completing, in the optional fields."
        )
    if composite:
        lines.append(
            "Add object_strategies, an object with one entry each for the cube, the horizontal "
            "bottle, the upright bottle and the pen, and release_or_completion_rule: how to "
            "finish and count all five placements. A summary that counts the objects of a type "
            'or names objects by letter ("two cubes", "cube A") is refused.'
        )
    lines += [
        "Keep every constraint that contradicts no other: posture, what to check in the "
        "images, depth, safety, the lift that completes the task.",
        "Required, each not empty:",
        *_fields(REQUIRED_FIELDS),
        "Optional, checked when given:",
        *_fields(CHECKED_FIELDS),
        *_profile_lines(),
        "Optional, in any form (a string, a list or an object):",
        *_fields(FREE_FIELDS),
        "Any other field you add is kept as you write it.",
        "",
        "# Reply format",
        "Reply with exactly one JSON object per reply, in a ```json block, for example:",
        '```json\n{"tool": "expert.frame", "args": {"steps": [0, 5, 10]}}\n```',
    ]
    return "\n".join(lines)


def first_turn(instruction: str, demo: DemoFrames) -> tuple[str, tuple[Image, ...]]:
    """The first user turn: the scene (its observation text, with its image), or the task
    when there is no scene; then the size of the video (and its parts, if several)."""
    n = len(demo)
    images: tuple[Image, ...] = ()
    if demo.scene is not None:
        lines = [
            "The scene at the start of the demonstration, as the evaluation's first "
            "observation shows it (its head-camera image follows this message):",
            "",
            demo.scene.text,
            "",
        ]
        images = (Image(demo.scene.image),)
    else:
        lines = [f"Task instruction: {instruction}"]
        if demo.composite:
            lines.append(
                "No scene of this task is shown: the videos below each show one skill it combines."
            )
    if not demo.videos:
        lines.append(f"The demonstration video has {n} frames (frame 0 to frame {n - 1}).")
    else:
        lines.append(f"The demonstration has {len(demo.videos)} videos, {n} frames in all:")
        ends = [k for k, _ in demo.videos[1:]] + [n]
        for j, ((first, title), end) in enumerate(zip(demo.videos, ends, strict=True), start=1):
            lines.append(f"- video {j}, frames {first} to {end - 1}: {title}")
    lines.append(
        "In this stage, reply with the demonstration tools only: list the frames with "
        "expert.retrieve, inspect them with expert.frame, then store your summary with "
        "expert.learn."
    )
    return "\n".join(lines), images


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


def gate_problems(demo: DemoFrames, retrieved: bool, inspected: Sequence[int]) -> list[str]:
    """Why `expert.learn` is refused yet (empty: the gate is passed): no `expert.retrieve`,
    fewer than `MIN_DISTINCT_FRAMES` distinct frames shown, or of some video."""
    problems = []
    if not retrieved:
        problems.append("learning gate: call expert.retrieve before expert.learn")
    seen = sorted(set(inspected))
    listed = ", ".join(map(str, seen)) or "none"
    if len(seen) < MIN_DISTINCT_FRAMES:
        problems.append(
            f"learning gate: inspect at least {MIN_DISTINCT_FRAMES} distinct demonstration "
            f"frames with expert.frame before expert.learn; distinct frames inspected so far: "
            f"{len(seen)} ({listed})"
        )
    if demo.composite:
        counts = {j: 0 for j in range(1, len(demo.videos) + 1)}
        for k in seen:
            counts[demo.locate(k)[0]] += 1
        short = [f"video {j} ({c})" for j, c in counts.items() if c < MIN_DISTINCT_FRAMES]
        if short:
            problems.append(
                f"learning gate: inspect at least {MIN_DISTINCT_FRAMES} distinct frames of every "
                f"video; distinct frames so far of those short of it: {', '.join(short)}"
            )
    return problems
