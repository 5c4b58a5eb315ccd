"""The plan of a sweep: every episode it must run (`plan`), once each, and what running them
may cost (`estimate`, what `--dry-run` prints: an upper bound, every episode at its whole step
budget). The order is fixed (the same config, the same list) and groups by task first, so that
the episodes one simulator batch serves come together:

    task (config order) > model (config order) > track (config order) > run > seed (config order)
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

from vabench.agent.usage import Assumptions, Usage, cost, episode_usage
from vabench.config import SweepConfig
from vabench.llm_pool.spend import Pricing, cost_text
from vabench.run_layout import episode_rel
from vabench.tasks import get_task

FIRST_RUN = 1  # as the paper numbers runs


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
    """The (model, summary family) learning sessions `keys` need, once each, in plan order: the
    model whose summary the track reads (own or shared) and the task's (a variant's base) family."""
    out: dict[tuple[str, str], None] = {}
    for key in keys:
        source = config.track(key.track).summary_source(key.model)
        if source is not None:
            out[(source, get_task(key.task).summary_family)] = None
    return list(out)


# -- the dry-run estimate ---------------------------------------------------------------------


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


def _ordered(counts: Counter[str], order: tuple[str, ...]) -> dict[str, int]:
    return {name: counts[name] for name in order if counts[name]}


# -- the table --------------------------------------------------------------------------------


def format_estimate(est: Estimate) -> str:
    """The dry-run report: episodes per model, track and task; calls, tokens, cost; assumptions."""
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
