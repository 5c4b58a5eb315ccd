"""The bill: what every model call of a sweep cost, not only the calls of recorded episodes.

The usage table counts scored episodes; a provider bills every call. This section adds up the
cost (US dollars at the configured prices, as the pool computed it per call) and tokens of
each place a call leaves a trace in the run directory, per model:

- scored episodes, unscored records: results.jsonl (status success/failure, or not);
- infrastructure failures run again: infrastructure.jsonl (each failed attempt's result);
- interrupted attempts: an events.jsonl without a result.json (a killed sweep's episodes, set
  aside as `partial_N/` when run again; episodes an endpoint refusal stopped): the cost of its
  `reply` and `compaction` events;
- duplicate records collapsed: results.duplicates.jsonl;
- learning sessions: summaries/<model>/<family>.json (each attempt it holds), and interrupted
  sessions' events.

Attempts whose usage never came back (a timeout, a dropped or cut connection: the provider may
still bill their input) are counted, not priced: `unknown_usage_attempts`.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vabench.llm_pool.settings import Prices
from vabench.llm_pool.spend import EMBEDDED_BASE_URL, Pricing, cost_cell, cost_text, pricing_of
from vabench.report.stats import TOKEN_FIELDS
from vabench.run_layout import (
    ATTEMPT_PREFIX,
    EPISODES,
    EVENTS,
    PARTIAL_PREFIX,
    SUMMARIES,
    EpisodeDir,
    RunDir,
)
from vabench.run_records import jsonl_objects
from vabench.tables import Csv, Section, Table

SOURCES = (
    "scored episodes",
    "unscored records",
    "infrastructure failures run again",
    "interrupted attempts",
    "duplicate records collapsed",
    "learning sessions",
)
_USAGE_KEYS = {
    "input": "input_tokens",
    "cached_input": "cached_input_tokens",
    "cache_write": "cache_write_tokens",
    "output": "output_tokens",
    "reasoning": "reasoning_tokens",
}
# Failure lines of attempts whose usage never came back
# (see vabench.llm_pool.transport.Transport.post).
_NO_USAGE = ("timeout", "ClientError", "ServerDisconnected", "ClientPayloadError", "Connection")


@dataclass
class Spend:
    """One (model, source): records or attempts, their cost and tokens."""

    model: str
    source: str
    items: int = 0
    cost_usd: float = 0.0
    tokens: dict[str, int] = field(default_factory=lambda: dict.fromkeys(TOKEN_FIELDS, 0))


@dataclass
class Bill:
    rows: list[Spend]
    unknown_usage_attempts: dict[str, int]
    """Per model: failed HTTP attempts whose usage is unknown (timeouts, cut connections)."""

    def total(self, model: str) -> float:
        return math.fsum(r.cost_usd for r in self.rows if r.model == model)


def _add_record(s: Spend, record: dict[str, Any]) -> None:
    s.items += 1
    s.cost_usd += float(record.get("cost_usd") or 0.0)
    tokens = record.get("tokens") or {}
    for name in TOKEN_FIELDS:
        s.tokens[name] += int(tokens.get(name) or 0)


def _add_calls(s: Spend, events: list[dict[str, Any]]) -> None:
    calls = [e for e in events if e.get("type") in ("reply", "compaction") and "usage" in e]
    if not events:
        return
    s.items += 1
    for e in calls:
        s.cost_usd += float(e.get("cost_usd") or 0.0)
        for name, key in _USAGE_KEYS.items():
            s.tokens[name] += int(e["usage"].get(key) or 0)


def _no_usage_failures(events: list[dict[str, Any]]) -> int:
    n = 0
    for e in events:
        if e.get("type") in ("reply", "llm_failure"):
            n += sum(1 for f in e.get("failures") or [] if any(m in f for m in _NO_USAGE))
    return n


def _interrupted_logs(run_dir: Path) -> Iterator[Path]:
    """events.jsonl of attempts that ended without a result: set-aside `partial_N/` logs,
    and episode or learning directories holding events but no result."""
    for events in run_dir.rglob(EVENTS):
        d = events.parent
        if d.name.startswith(ATTEMPT_PREFIX):
            continue  # a finished attempt: its result is in infrastructure.jsonl
        if d.name.startswith(PARTIAL_PREFIX) or not EpisodeDir(d).finished():
            yield events


def _model_of(run_dir: Path, events_file: Path, events: list[dict[str, Any]]) -> str | None:
    for e in events:
        if e.get("type") in ("episode_start", "learning_start") and e.get("model"):
            return str(e["model"])
    parts = events_file.relative_to(run_dir).parts
    if len(parts) > 1 and parts[0] in (EPISODES, SUMMARIES):
        return parts[1]
    return None


def bill(run_dir: Path | str, *, unknown_usage: bool = True) -> Bill:
    """Every source of the module docstring, per model; `unknown_usage=False` skips counting
    the attempts whose usage never came back (a read of every events.jsonl, which the sweep's
    spend caps, reading the bill on resume, do not need)."""
    run_dir = Path(run_dir)
    files = RunDir(run_dir)
    rows: dict[tuple[str, str], Spend] = {}
    unknown: dict[str, int] = defaultdict(int)

    def row(model: str, source: str) -> Spend:
        return rows.setdefault((model, source), Spend(model, source))

    for record in jsonl_objects(files.results):
        scored = record.get("status") in ("success", "failure")
        _add_record(row(str(record.get("model")), SOURCES[0 if scored else 1]), record)
    for record in jsonl_objects(files.infrastructure):
        _add_record(row(str(record.get("model")), SOURCES[2]), record)
    for record in jsonl_objects(files.duplicates):
        _add_record(row(str(record.get("model")), SOURCES[4]), record)
    for path in files.summary_files():
        try:
            learned = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            continue
        learner = str(learned.get("model") or path.parent.name)
        for attempt in [*(learned.get("earlier_attempts") or []), learned]:
            _add_record(row(learner, SOURCES[5]), attempt)
    for events_file in sorted(_interrupted_logs(run_dir)):
        events = list(jsonl_objects(events_file))
        model = _model_of(run_dir, events_file, events)
        if model is None:
            continue
        learning = events_file.relative_to(run_dir).parts[0] == SUMMARIES
        _add_calls(row(model, SOURCES[5] if learning else SOURCES[3]), events)
    for events_file in run_dir.rglob(EVENTS) if unknown_usage else ():
        events = list(jsonl_objects(events_file))
        if (n := _no_usage_failures(events)) and (m := _model_of(run_dir, events_file, events)):
            unknown[m] += n
    order = {s: i for i, s in enumerate(SOURCES)}
    ordered = sorted(rows.values(), key=lambda r: (r.model, order[r.source]))
    return Bill(ordered, dict(sorted(unknown.items())))


def recorded_spend(run_dir: Path | str) -> dict[str, float]:
    """US dollars per model of every call the run directory holds a trace of (the bill's
    sources): what a spend cap counts as already spent when a sweep resumes."""
    b = bill(run_dir, unknown_usage=False)
    return {m: b.total(m) for m in {r.model for r in b.rows}}


def model_pricing(run_dir: Path | str) -> dict[str, Pricing]:
    """How each model of the run directory's sweep.yaml is priced (empty without one: costs
    then show as numbers). Read as YAML, not as a `SweepConfig`: the report sits below the
    config package and needs only these two fields of each model."""
    try:
        doc = yaml.safe_load(RunDir(Path(run_dir)).config.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return {}
    models = doc.get("models") if isinstance(doc, dict) else None
    return {
        str(m["name"]): pricing_of(
            Prices.model_validate(m["prices"]) if m.get("prices") else None,
            m.get("base_url") == EMBEDDED_BASE_URL,
        )
        for m in models or ()
        if isinstance(m, dict) and "name" in m
    }


def spend_section(b: Bill, pricing: Mapping[str, Pricing] | None = None) -> Section | None:
    """The "Spend of every call" section; None when no call left a trace (no tokens, no
    cost anywhere: a bill of nothing)."""
    if not any(r.cost_usd or any(r.tokens.values()) for r in b.rows):
        return None
    known = pricing or {}

    def usd(value: float, model: str) -> str:
        return cost_text(value, {model: known[model]} if model in known else {}, ".4f", sign="")

    rows, csv_rows = [], []
    for model in sorted({r.model for r in b.rows}):
        mine = [r for r in b.rows if r.model == model]
        for r in mine:
            tokens = sum(r.tokens.values()) - r.tokens["reasoning"]  # reasoning is in output
            rows.append([model, r.source, str(r.items), f"{tokens:,}", usd(r.cost_usd, model)])
            cell = cost_cell(r.cost_usd, known.get(model))
            csv_rows.append([model, r.source, r.items, *(r.tokens[n] for n in TOKEN_FIELDS), cell])
        # the total row sums every column (its records and tokens too: they read as blanks)
        items = sum(r.items for r in mine)
        token_sums = {n: sum(r.tokens[n] for r in mine) for n in TOKEN_FIELDS}
        shown = sum(token_sums.values()) - token_sums["reasoning"]
        rows.append([model, "total", str(items), f"{shown:,}", usd(b.total(model), model)])
        total_cell = cost_cell(b.total(model), known.get(model))
        csv_rows.append([model, "total", items, *(token_sums[n] for n in TOKEN_FIELDS), total_cell])
    notes = [
        "every call the sweep made, by where its trace lies: the usage table counts scored "
        "episodes only; this is the bill"
    ]
    for model, n in b.unknown_usage_attempts.items():
        notes.append(
            f"{model}: {n} call attempt(s) timed out or lost their connection; their usage never "
            "came back (not priced above; a provider may bill their input)"
        )
    return Section(
        "spend",
        "Spend of every call",
        [Table("Spend", ["model", "source", "records / attempts", "tokens", "cost USD"], rows)],
        [
            Csv(
                "spend",
                ["model", "source", "items", *(f"tokens_{n}" for n in TOKEN_FIELDS), "cost_usd"],
                csv_rows,
            )
        ],
        notes,
    )
