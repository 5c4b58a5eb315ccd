"""An episode's model usage estimated before it runs: the engine's conversation replayed with
stand-in images and replies (`episode_usage`), under these assumptions (`Assumptions`):

- every episode uses its whole step budget (the task's, capped by `step_budget`), one model
  call per step, plus `extra_call_share` calls per step for repairs and tools (default 0; set
  it from a measured run); an extra call costs what the step's call costs;
- each call's input is the episode's context as the engine builds it: the system prompt, the
  observation texts (made by the real prompt code, with a typical robot state and one typical
  executed-action line per step so far), the replies so far, and the images the conversation
  retains (the last 4 in the active protocol, the current five-view bundle in the passive one)
  at the configured resolution, priced in tokens by the API's image rule (its registered
  adapter's `image_tokens`, which the pool's TPM estimate uses too); the conversation
  compacts as the engine's does, and each compaction is one more call;
- every reply is `output_tokens` long (default 150), a compaction summary `summary_tokens`;
- a `cached_input_share` of the input tokens is billed at the model's cached-input price
  (default 0: no caching, an upper bound for providers that cache prompt prefixes).

Cost = input x input price + output x output price (US dollars per million tokens, `cost`).
"""

from __future__ import annotations

import functools
from collections.abc import Coroutine
from dataclasses import dataclass
from typing import Any, cast

from vabench import protocol as P
from vabench.agent.conversation import Conversation
from vabench.agent.observation import (
    PASSIVE_VIEWS,
    TYPICAL_PROPRIO,
    ActionFeedback,
    observation_text,
)
from vabench.agent.prompts import system_prompt
from vabench.llm_pool.apis import get_adapter
from vabench.llm_pool.config import ApiName, Prices
from vabench.llm_pool.messages import ChatRequest, Image
from vabench.llm_pool.tokens import (
    CHARS_PER_TOKEN,
    ImageTokenRule,
    estimate_input_tokens,
    stand_in_jpeg,
)
from vabench.tasks import get_task


@dataclass(frozen=True)
class Assumptions:
    """The free parameters of `estimate` (see the module docstring)."""

    output_tokens: int = 150
    """Tokens of one reply."""
    extra_call_share: float = 0.0
    """Repair and tool calls per environment step."""
    summary_tokens: int = 600
    """Tokens of one compaction summary (the instruction asks for about 400 words)."""
    cached_input_share: float = 0.0
    """Share of input tokens billed at the cached-input price."""

    def __post_init__(self) -> None:
        if self.output_tokens < 1 or self.summary_tokens < 1:
            raise ValueError("output_tokens and summary_tokens must be >= 1")
        if self.extra_call_share < 0:
            raise ValueError(f"extra_call_share must be >= 0, got {self.extra_call_share}")
        if not 0 <= self.cached_input_share <= 1:
            raise ValueError(f"cached_input_share must be in [0, 1], got {self.cached_input_share}")


@dataclass(frozen=True)
class Usage:
    """Estimated calls and tokens (of one episode, or summed)."""

    calls: float = 0.0
    input_tokens: float = 0.0
    output_tokens: float = 0.0

    def __add__(self, other: Usage) -> Usage:
        return Usage(
            self.calls + other.calls,
            self.input_tokens + other.input_tokens,
            self.output_tokens + other.output_tokens,
        )

    def __mul__(self, n: float) -> Usage:
        return Usage(self.calls * n, self.input_tokens * n, self.output_tokens * n)


def cost(usage: Usage, prices: Prices, a: Assumptions) -> float:
    """US dollars of `usage` at `prices` (per million tokens)."""
    cached_price = prices.input if prices.cached_input is None else prices.cached_input
    fresh = usage.input_tokens * (1 - a.cached_input_share)
    cached = usage.input_tokens * a.cached_input_share
    return (
        fresh * prices.input + cached * cached_price + usage.output_tokens * prices.output
    ) / 1e6


@functools.lru_cache(maxsize=256)
def episode_usage(
    task: str, track: str, budget: int, image_size: tuple[int, int], api: ApiName, a: Assumptions
) -> Usage:
    """Estimated usage of one episode of `task` under `track` that runs `budget` steps (see the
    module docstring): replays the engine's conversation with stand-in images and replies."""
    rule = get_adapter(api).image_tokens
    return _run_without_loop(_replay(task, track, budget, image_size, rule, a))


def _run_without_loop(coro: Coroutine[Any, Any, Usage]) -> Usage:
    """Run a coroutine that never suspends (the summarizer it awaits returns at once), so that
    `estimate` works with or without a running event loop (asyncio.run refuses inside one)."""
    try:
        coro.send(None)
    except StopIteration as done:
        return done.value  # type: ignore[no-any-return]
    coro.close()
    raise RuntimeError("the conversation replay suspended")


async def _replay(
    task_name: str,
    track: str,
    budget: int,
    image_size: tuple[int, int],
    rule: ImageTokenRule,
    a: Assumptions,
) -> Usage:
    task = get_task(task_name)
    arms = tuple(task.arms)
    tools = P.available_tools(demonstration=False)
    if track == "passive":  # as the engine: passive requests carry only the current bundle
        tools = tuple(t for t in tools if t != "camera.history")
    # The engine's Conversation estimates with the OpenAI rule when deciding to compact, so
    # this one does too; the billed tokens below use the API's own rule.
    protocol = cast(P.ObservationProtocol, track)
    conv = Conversation(system_prompt(arms, track, list(tools), task=task_name), protocol=protocol)
    available = P.available_actions(arms, protocol, tools)
    jpeg = stand_in_jpeg(*image_size)
    reply = "x" * int(a.output_tokens * CHARS_PER_TOKEN)
    summary = "x" * int(a.summary_tokens * CHARS_PER_TOKEN)
    usage = Usage()

    async def summarize(request: ChatRequest) -> str:
        nonlocal usage
        usage += Usage(1, estimate_input_tokens(request, rule), a.summary_tokens)
        return summary

    for step in range(1, budget + 1):
        text = observation_text(
            step=step,
            step_budget=budget,
            instruction=task.instruction,
            proprio={arm: TYPICAL_PROPRIO for arm in arms},
            arms=arms,
            feedback=ActionFeedback(True, True) if step > 1 else ActionFeedback(),
            executed_actions=[_TYPICAL_ACTION] * (step - 1),
            demonstration_summary=None,
            available_actions=available,
        )
        # New Image objects each time: the conversation sends one object only once.
        images = Image(jpeg) if track == "active" else {v: Image(jpeg) for v in PASSIVE_VIEWS}
        conv.add_observation(text, images, step=step)
        await conv.compact_if_needed(summarize)
        calls = 1 + a.extra_call_share
        usage += Usage(
            calls, calls * estimate_input_tokens(conv.request(), rule), calls * a.output_tokens
        )
        conv.add_reply(reply)
    return usage


_TYPICAL_ACTION = "move_world z-30mm"
