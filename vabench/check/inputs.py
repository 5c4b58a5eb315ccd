"""The check's request: the heaviest a sweep sends one model, built from the sweep's own inputs.

One decision carries what the model's requests carry at their largest:

- the longest first-step prompt of the model's (track, task) pairs: the system prompt and the
  first observation as the engine writes them (a stand-in robot state, no summary yet);
- the images at their real size: the passive five-view bundle (or the active view) at the
  configured resolution and JPEG quality, a synthetic scene of a rendered frame's detail (the
  check renders nothing), then, where a track reads summaries, the learning stage's
  demonstration frames (the cached video's own, else 1280x960 stand-ins), up to the most images
  one request of the sweep holds: the passive bundle (5), the active protocol's retained images
  (4), a learning request's kept and newly shown frames (8 + 8).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np

from vabench import protocol as P
from vabench.agent.conversation import ContextLimits
from vabench.agent.learning import LearningLimits
from vabench.agent.observation import (
    PASSIVE_VIEWS,
    TYPICAL_PROPRIO,
    ActionFeedback,
    observation_text,
)
from vabench.agent.prompts import system_prompt
from vabench.config import SweepConfig, Track
from vabench.demos.store import load_demo
from vabench.llm_pool.apis import get_adapter
from vabench.llm_pool.config import GenerationOptions
from vabench.llm_pool.messages import ChatRequest, Image, Turn
from vabench.llm_pool.tokens import (
    CHARS_PER_TOKEN,
    estimate_input_tokens,
    image_size,
    text_tokens,
)
from vabench.render.images import encode_jpeg
from vabench.tasks import get_task

DEMO_SIZE = (1280, 960)
"""Demonstration frames' size (`vabench.demos.build.DEMO_SETTINGS`)."""
DEMO_QUALITY = 90
LEAST_IMAGE_TOKENS = 256
"""Fewest tokens a multimodal model counts for an image of 640x480 or more (Gemini: 258 for
any image; Qwen-VL one per 28x28 patch, Claude one per 750 pixels, GPT 85 + 170 a tile: far
more). A smaller image counts at least one per `LEAST_PIXELS_PER_TOKEN` pixels. A prompt
counted below the floor these give lost images or text on the way in."""
LEAST_PIXELS_PER_TOKEN = 800
TEXT_SHARE_COUNTED = 0.75
"""The share of our text estimate every tokenizer counts at least (ours: 4 characters a
token; real tokenizers count English prose and JSON at 3-5)."""
CONTEXT_PROBE_TOKENS = 16_384
"""The fewest tokens the context probe's prompt holds (at most what an episode may reach): a
silent cut below it (Ollama's default num_ctx of 2,048-8,192, llama.cpp's -c) shows in the
count, at the price of one long text-only prompt."""

"""A robot state of the real one's length (numbers as the observation prints them)."""


@dataclass(frozen=True)
class Probe:
    """One model's check request and what it holds."""

    request: ChatRequest
    where: str
    """The (track, task) whose first step is the prompt."""
    images_why: str
    """Which of the sweep's requests carries this many images."""
    text_tokens: int
    """Our estimate of the text (system prompt and observation)."""
    least_tokens: int
    """The fewest prompt tokens an honest server can count for it."""

    @property
    def images(self) -> int:
        return len(self.request.images)

    def estimate(self, api: str) -> int:
        """Our estimate of its prompt tokens under `api`'s image rule."""
        return estimate_input_tokens(self.request, get_adapter(api).image_tokens)


def least_image_tokens(width: int, height: int) -> int:
    """The fewest prompt tokens any multimodal model counts for an image of this size."""
    return min(LEAST_IMAGE_TOKENS, width * height // LEAST_PIXELS_PER_TOKEN)


def first_step_prompt(config: SweepConfig, track: str, task_name: str) -> tuple[str, str]:
    """(system prompt, first observation) of an episode of `task_name` on `track`."""
    task = get_task(task_name)
    protocol = cast(Track, config.track(track).protocol)
    arms = tuple(task.arms)
    tools = P.available_tools(demonstration=False)
    if protocol == "passive":  # as the engine: passive requests carry only the current bundle
        tools = tuple(t for t in tools if t != "camera.history")
    text = observation_text(
        step=1,
        step_budget=config.budget(task_name),
        instruction=task.instruction,
        proprio={arm: TYPICAL_PROPRIO for arm in arms},
        arms=arms,
        feedback=ActionFeedback(),
        executed_actions=[],
        demonstration_summary=None,
        available_actions=P.available_actions(arms, protocol, tools),
    )
    return system_prompt(arms, protocol, list(tools), task=task_name), text


def scene_jpeg(
    width: int, height: int, quality: int, subsampling: str = "420", seed: int = 0
) -> bytes:
    """A JPEG of a rendered frame's size and detail: a lit table, a few objects, sensor noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    base = 90 + 80 * (y / height)[..., None] * np.array([1.0, 0.9, 0.8], np.float32)
    pixels = base + 12 * np.sin(x / 23.0)[..., None]
    for _ in range(6):  # objects: boxes of flat colour
        x0, y0 = int(rng.integers(0, width * 3 // 4)), int(rng.integers(0, height * 3 // 4))
        pixels[y0 : y0 + height // 6, x0 : x0 + width // 8] = rng.integers(20, 235, 3)
    pixels += 6 * rng.standard_normal(pixels.shape, dtype=np.float32)
    return encode_jpeg(np.clip(pixels, 0, 255).astype(np.uint8), quality, subsampling)


def demo_frames(config: SweepConfig, tasks: list[str], n: int) -> list[bytes]:
    """`n` demonstration frames: the first cached video's of `tasks`, else stand-ins."""
    cache = config.learning.cache_path()
    for name in tasks:
        try:
            frames = load_demo(get_task(name).summary_family, cache).frames
        except (FileNotFoundError, ValueError, KeyError):
            continue
        if frames:
            return [frames[k % len(frames)] for k in range(n)]
    width, height = DEMO_SIZE
    distinct = [scene_jpeg(width, height, DEMO_QUALITY, seed=k) for k in range(min(n, 4))]
    return [distinct[k % len(distinct)] for k in range(n)]


def probe(config: SweepConfig, model: str, tracks: list[str] | None = None) -> Probe:
    """The check request of `model` over `tracks` (default: the config's)."""
    tracks = list(config.track_names) if tracks is None else tracks
    pairs = [(t, task) for t in tracks for task in config.track_tasks(t)]
    if not pairs:
        raise ValueError(f"model {model!r}: no track of the plan runs a task")
    prompts = {pair: first_step_prompt(config, *pair) for pair in pairs}
    (track, task), (system, text) = max(prompts.items(), key=lambda kv: len("".join(kv[1])))
    protocols = {config.track(t).protocol for t in tracks}
    learning = [t for t in tracks if config.track(t).summary_source(model) is not None]
    peaks = {}
    if "passive" in protocols:
        peaks["the passive five-view bundle"] = len(PASSIVE_VIEWS)
    if "active" in protocols:
        peaks["the active protocol's retained views"] = ContextLimits().max_images
    if learning:
        kept = LearningLimits().context.max_images
        peaks[f"a learning request ({kept} frames kept, {P.MAX_EXPERT_FRAMES} newly shown)"] = (
            kept + P.MAX_EXPERT_FRAMES
        )
    why, most = max(peaks.items(), key=lambda kv: kv[1])
    r = config.render
    views = len(PASSIVE_VIEWS) if "passive" in protocols else 1
    jpegs = [scene_jpeg(r.width, r.height, r.quality, r.subsampling, seed=k) for k in range(views)]
    names = [name for t in learning for name in config.track_tasks(t)]
    jpegs += demo_frames(config, names, most - len(jpegs)) if most > len(jpegs) else []
    jpegs += [jpegs[k % len(jpegs)] for k in range(most - len(jpegs))]
    images = [Image(j) for j in jpegs]
    request = ChatRequest(turns=(Turn.user(text, *images),), system=system)
    least = TEXT_SHARE_COUNTED * (text_tokens(system) + text_tokens(text))
    least += sum(least_image_tokens(*image_size(i)) for i in images)
    return Probe(
        request,
        f"{track}/{task}",
        why,
        text_tokens(system) + text_tokens(text),
        int(least),
    )


def context_probe(least: int) -> tuple[ChatRequest, int]:
    """A text-only request that every tokenizer counts at `least` tokens or more, and that
    floor: numbered lines of plain prose, so that no cache or tokenizer shortcut shrinks it."""
    chars = least / TEXT_SHARE_COUNTED * CHARS_PER_TOKEN  # what `text_tokens` counts as `least`
    lines: list[str] = []
    size = 0
    while size < chars:
        n = len(lines) + 1
        lines.append(f"Line {n}: the gripper moves {n % 97 + 3} millimetres along x.\n")
        size += len(lines[-1])
    prompt = "".join(lines) + "Reply with the number of the last line only."
    options = GenerationOptions(max_output_tokens=16)
    request = ChatRequest(turns=(Turn.user(prompt),), options=options)
    return request, int(TEXT_SHARE_COUNTED * text_tokens(prompt))
