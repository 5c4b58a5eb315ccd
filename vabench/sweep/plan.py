"""The plan of a sweep: every episode it must run, and what running them may cost.

`plan(config)` lists one `EpisodeKey` per (model, track, task, seed, run): models x tracks x
the track's tasks x seeds of the task x runs, each exactly once. The order is fixed (the same
config always gives the same list) and groups by task first, so that the episodes one simulator
batch serves come together:

    task (config order) > model (config order) > track (config order) > run > seed (config order)

Runs are numbered from `FIRST_RUN` (1), as the paper numbers them.

`estimate(config, keys)` is what `--dry-run` prints: episodes per model, track and task, and an
estimate of model calls, tokens and cost, under these assumptions (`Assumptions`):

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

Cost = input x input price + output x output price (US dollars per million tokens); a model
without `prices` shows "price not set", one of the embedded server "no cost"
(`llm_pool.spend.cost_text`).
"""

from __future__ import annotations

import functools
import math
from collections import Counter
from collections.abc import Coroutine
from dataclasses import dataclass, field
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
from vabench.config import SweepConfig, Track
from vabench.llm_pool.apis import get_adapter
from vabench.llm_pool.config import ApiName, Prices
from vabench.llm_pool.messages import ChatRequest, Image
from vabench.llm_pool.spend import Pricing, cost_text
from vabench.llm_pool.tokens import CHARS_PER_TOKEN, ImageTokenRule, estimate_input_tokens
from vabench.run_layout import episode_rel
from vabench.tasks import get_task

FIRST_RUN = 1


@dataclass(frozen=True, order=True)
class EpisodeKey:
    """One planned episode. Ordered field by field (model, track, task, seed, run)."""

    model: str
    track: str
    task: str
    seed: int
    run: int

    @property
    def rel_dir(self) -> str:
        """The episode's directory under the run directory."""
        return episode_rel(self.model, self.track, self.task, self.seed, self.run)

    def as_id(self) -> str:
        """A one-line id for logs and progress: `model/track/task/seed/run`."""
        return f"{self.model}/{self.track}/{self.task}/{self.seed}/{self.run}"


def plan(config: SweepConfig) -> list[EpisodeKey]:
    """Every episode of the sweep, once each, in the order of the module docstring."""
    return [
        EpisodeKey(model.name, track.name, task, seed, run)
        for task in config.all_tasks
        for model in config.models
        for track in config.tracks
        if task in config.track_tasks(track)
        for run in range(FIRST_RUN, FIRST_RUN + config.runs)
        for seed in config.seeds[task]
    ]


def learning_sessions(config: SweepConfig, keys: list[EpisodeKey]) -> list[tuple[str, str]]:
    """The (model, summary family) learning sessions `keys` need, each once, in plan order:
    the model whose summary the episode's track reads (its own, or the shared source) and the
    family whose summary the task reads (a held-out variant: its base family)."""
    out: dict[tuple[str, str], None] = {}
    for key in keys:
        source = config.track(key.track).summary_source(key.model)
        if source is not None:
            out[(source, get_task(key.task).summary_family)] = None
    return list(out)


# -- the dry-run estimate ---------------------------------------------------------------------


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


@dataclass(frozen=True)
class ModelEstimate:
    model: str
    episodes: int
    usage: Usage
    cost_usd: float
    pricing: Pricing = Pricing.SET


@dataclass(frozen=True)
class Estimate:
    episodes: int
    by_model: dict[str, int]
    by_track: dict[str, int]
    by_task: dict[str, int]
    """Episode counts, in the config's order."""
    models: list[ModelEstimate]
    assumptions: Assumptions = field(default_factory=Assumptions)
    learning: dict[str, int] = field(default_factory=dict)
    """Learning sessions per model (`learning_sessions`)."""
    learning_calls_max: int = 30

    @property
    def usage(self) -> Usage:
        return sum((m.usage for m in self.models), Usage())

    @property
    def cost_usd(self) -> float:
        return sum(m.cost_usd for m in self.models)


def estimate(
    config: SweepConfig, keys: list[EpisodeKey], assumptions: Assumptions | None = None
) -> Estimate:
    """Counts and the cost estimate of running `keys` (usually `plan(config)`)."""
    a = assumptions or Assumptions()
    size = (config.render.width, config.render.height)
    per_model: dict[str, Usage] = {}
    for key in keys:
        api = config.model(key.model).api
        protocol = config.track(key.track).protocol
        one = episode_usage(key.task, protocol, config.budget(key.task), size, api, a)
        per_model[key.model] = per_model.get(key.model, Usage()) + one
    by_model = Counter(k.model for k in keys)
    pricing = config.pricing()
    models = [
        ModelEstimate(
            m.name,
            by_model[m.name],
            per_model[m.name],
            cost(per_model[m.name], m.prices, a) if m.prices is not None else 0.0,
            pricing[m.name],
        )
        for m in config.models
        if m.name in per_model
    ]
    return Estimate(
        episodes=len(keys),
        by_model={m: by_model[m] for m in (x.name for x in config.models) if by_model[m]},
        by_track=_ordered(Counter(k.track for k in keys), config.track_names),
        by_task=_ordered(Counter(k.task for k in keys), config.all_tasks),
        models=models,
        assumptions=a,
        learning=dict(Counter(m for m, _ in learning_sessions(config, keys))),
        learning_calls_max=config.learning.max_model_calls,
    )


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
    protocol = cast(Track, track)
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


def stand_in_jpeg(width: int, height: int) -> bytes:
    """The header of a baseline JPEG of this size: all the token estimators read of an image."""
    sof = b"\xff\xc0\x00\x11\x08" + height.to_bytes(2, "big") + width.to_bytes(2, "big")
    sof += b"\x03" + b"\x01\x22\x00\x02\x11\x01\x03\x11\x01"  # three components
    return b"\xff\xd8" + sof + b"\xff\xd9"


def _ordered(counts: Counter[str], order: tuple[str, ...]) -> dict[str, int]:
    return {name: counts[name] for name in order if counts[name]}


# -- the table --------------------------------------------------------------------------------


def format_estimate(est: Estimate) -> str:
    """The dry-run report: episodes per model, track and task, then calls, tokens and cost per
    model with a total, then the assumptions."""
    lines = [f"Planned episodes: {est.episodes}"]
    for title, counts in (("model", est.by_model), ("track", est.by_track), ("task", est.by_task)):
        lines += [
            "",
            _table([title.capitalize(), "Episodes"], [[k, f"{v:,}"] for k, v in counts.items()]),
        ]
    rows = [[m.model, f"{m.episodes:,}", *_usage_cells(m.usage), cost_of(m)] for m in est.models]
    total = _cost(est.cost_usd, {m.model: m.pricing for m in est.models})
    rows.append(["total", f"{est.episodes:,}", *_usage_cells(est.usage), total])
    header = ["Model", "Episodes", "Calls", "Input tokens", "Output tokens", "Cost (USD)"]
    a = est.assumptions
    lines += [
        "",
        "Estimate (upper bound: every episode uses its whole step budget):",
        _table(header, rows),
        "",
        f"Assumptions: one call per step + {a.extra_call_share:g} repair/tool calls per step; "
        f"{a.output_tokens} output tokens per call; {a.summary_tokens} per compaction summary; "
        f"{a.cached_input_share:.0%} of input billed as cached.",
    ]
    if est.learning:
        sessions = ", ".join(f"{m}: {n}" for m, n in est.learning.items())
        lines += [
            "",
            f"Learning stage: {sum(est.learning.values())} sessions, one per (model, family) "
            f"({sessions}); each at most {est.learning_calls_max} calls (a diligent model needs "
            "3-8), over 640x480 demonstration frames; not included above.",
        ]
    return "\n".join(lines)


def cost_of(m: ModelEstimate) -> str:
    return _cost(m.cost_usd, {m.model: m.pricing})


def _cost(usd: float, pricing: dict[str, Pricing]) -> str:
    return cost_text(usd, pricing, ",.2f", sign="")


def _usage_cells(u: Usage) -> list[str]:
    return [
        f"{math.ceil(u.calls):,}",
        f"{math.ceil(u.input_tokens):,}",
        f"{math.ceil(u.output_tokens):,}",
    ]


def _table(header: list[str], rows: list[list[str]]) -> str:
    """Left-aligned first column, right-aligned numbers."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(cells: list[str]) -> str:
        first = cells[0].ljust(widths[0])
        return "  ".join([first, *(c.rjust(w) for c, w in zip(cells[1:], widths[1:], strict=True))])

    return "\n".join([line(header), "  ".join("-" * w for w in widths), *(line(r) for r in rows)])
