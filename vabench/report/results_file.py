"""report/results.json and report/episode_outcomes.csv: a run's results in a documented, versioned
schema (docs/RESULTS.md; the JSON schema beside this module, `results.schema.json`).

results.json holds every scored and unscored episode (model, track, task, run, seed, outcome,
stop reason, reply counters), the aggregates with the formulas that made them, per-model
counts, the published reference rows when shown, and the provenance that decides whether two
runs' numbers may be compared: vabench's version and commit, the model-facing protocol's
version, physics backend and action timing, renderer and image settings, the protocol's
budgets, tracks, tasks, seeds and the config's hash. `comparability` is the part of the
provenance a leaderboard checks (`leaderboard`).

The run's files are read as YAML and JSON, not as a `SweepConfig`: the report sits below the
config package, and a run directory made by hand (results.jsonl alone) still gets a file,
with what it cannot know as null.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from collections.abc import Mapping, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import yaml

import vabench
from vabench.agent.generation import REASONING_EFFORT, THINKING_BUDGET
from vabench.llm_pool.settings import OFF
from vabench.protocol.version import PROTOCOL_VERSION
from vabench.protocol.vocabulary import MAX_REPAIRS_PER_DECISION, MAX_TOOL_ROUND_TRIPS
from vabench.report import published as P
from vabench.report.stats import Cell, Macro, Spread
from vabench.run_layout import RunDir
from vabench.run_records import Record

SCHEMA = "vabench.results"
SCHEMA_VERSION = 1
RESULTS_FILE = "results.json"
EPISODES_CSV = "episode_outcomes"
SCHEMA_FILE = Path(__file__).with_name("results.schema.json")
COUNTERS = ("invalid_outputs", "refusals", "truncations", "empty_replies")
"""Per-episode reply counters; a result written before a counter existed reads as 0."""
COMPARABLE = (
    "protocol_version",
    "tracks",
    "tasks",
    "seeds",
    "budgets",
    "image",
    "physics",
    "action_end",
)
"""What must match for two runs' scores to share a table (the leaderboard refuses otherwise)."""
FORMULAS = {
    "task_rate": "S(m,t,r,task) = successes / scored episodes of that model, track, run, task "
    "(infrastructure failures are re-run, never scored)",
    "macro_run": "M(m,t,r,subset) = unweighted mean of S(m,t,r,task) over the families of the "
    "subset present in run r (single: one arm, dual: more than one, all)",
    "macro": "mean and sample SD (divisor n - 1) of M(m,t,r,subset) over runs r; sd null for "
    "one run (the paper's eq. base-success)",
    "task": "mean and sample SD over runs of S(m,t,r,task)",
}


def counter(record: Record, name: str) -> int:
    return int(getattr(record.result, name, 0) or 0)


def _git_commit() -> str | None:
    """The commit of the vabench checkout writing the report (None outside a git checkout)."""
    root = Path(vabench.__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def _yaml(path: Path) -> dict[str, Any]:
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _section(doc: Mapping[str, Any], key: str) -> dict[str, Any]:
    value = doc.get(key)
    return value if isinstance(value, dict) else {}


def _plan_fields(run: RunDir) -> dict[str, Any]:
    try:
        plan = json.loads(run.plan.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    fields = plan.get("fields") if isinstance(plan, dict) else None
    return fields if isinstance(fields, dict) else {}


def api_setting_notes(run_dir: Path) -> list[str]:
    """A note for each model whose config changed one of the benchmark's API defaults
    (`vabench.agent.generation`): its scores were made under other settings than the paper's
    runs. Read from the plan's model entries (the generation options their configs name)."""
    notes = []
    defaults = {"reasoning_effort": REASONING_EFFORT, "thinking_budget": THINKING_BUDGET}
    for model in _plan_fields(RunDir(run_dir)).get("models") or []:
        generation = model.get("generation") if isinstance(model, dict) else None
        if not isinstance(generation, dict):
            continue
        for option, default in defaults.items():
            value = generation.get(option)
            if value is None or value == default:
                continue
            sent = "not sent" if value == OFF else f"{value} sent"
            notes.append(
                f"{model.get('name')}: generation.{option} {value} ({sent}; the benchmark's "
                f"default is {default}, where the model's API takes the option)"
            )
    return notes


def provenance(run_dir: Path, records: Sequence[Record]) -> dict[str, Any]:
    """How the run was made (see the module docstring); null where its files do not say."""
    run = RunDir(run_dir)
    doc = _yaml(run.config)
    plan = _plan_fields(run)
    try:
        config_bytes: bytes | None = run.config.read_bytes()
    except OSError:
        config_bytes = None
    render = _section(doc, "render")
    simulator = _section(doc, "simulator")
    budgets: dict[str, set[int]] = {}
    seeds_seen: dict[str, set[int]] = {}
    for rec in records:
        budgets.setdefault(rec.result.task, set()).add(rec.result.step_budget)
        seeds_seen.setdefault(rec.result.task, set()).add(rec.result.seed)
    seeds = doc.get("seeds") if isinstance(doc.get("seeds"), dict) else None
    tracks = doc.get("tracks") if isinstance(doc.get("tracks"), list) else None
    if tracks is not None:  # a hand-written config may name a track by its name alone
        tracks = [{"name": t} if isinstance(t, str) else t for t in tracks]
    else:
        protocols = {rec.track: rec.result.protocol for rec in records}
        tracks = [{"name": t, "protocol": p} for t, p in sorted(protocols.items())]
    recorded = plan.get("protocol_version")
    comparability = {
        "protocol_version": recorded or PROTOCOL_VERSION,
        "tracks": tracks,
        "tasks": doc.get("tasks") or sorted(seeds_seen),
        "seeds": {t: sorted(map(int, s)) for t, s in (seeds or seeds_seen).items()},
        "budgets": {
            "max_repairs_per_decision": MAX_REPAIRS_PER_DECISION,
            "max_tool_round_trips": MAX_TOOL_ROUND_TRIPS,
            "step_budget_cap": doc.get("step_budget"),
            "step_budgets": {t: sorted(b) for t, b in sorted(budgets.items())},
        },
        "image": {
            "width": render.get("width"),
            "height": render.get("height"),
            "jpeg_quality": render.get("quality"),
            "jpeg_subsampling": render.get("subsampling"),
        },
        "physics": simulator.get("backend"),
        # How long an action's physics runs decides where objects are when a model looks; a
        # sweep.yaml written before the field existed ran every action for the fixed time.
        "action_end": simulator.get("action_end") or "fixed",
    }
    return {
        "vabench_version": vabench.__version__,
        "vabench_commit": _git_commit(),
        "protocol_version": comparability["protocol_version"],
        "protocol_version_source": "plan" if recorded else "report",
        "physics_backend": simulator.get("backend"),
        "renderer": render.get("backend"),
        "runs": sorted({rec.result.run for rec in records}),
        "config_sha256": None if config_bytes is None else hashlib.sha256(config_bytes).hexdigest(),
        "run_dir": str(run_dir),
        "comparability": comparability,
    }


def _num(x: Fraction | float | None) -> float | None:
    return None if x is None else float(x)


def episode_row(rec: Record) -> dict[str, Any]:
    r = rec.result
    return {
        "model": r.model,
        "track": rec.track,
        "task": r.task,
        "run": r.run,
        "seed": r.seed,
        "protocol": r.protocol,
        "status": r.status,
        "scored": r.scored,
        "success": r.success,
        "stop_reason": r.stop_reason,
        "steps_used": r.steps_used,
        "step_budget": r.step_budget,
        **{name: counter(rec, name) for name in COUNTERS},
    }


def model_counts(records: Sequence[Record]) -> list[dict[str, Any]]:
    by: dict[str, dict[str, Any]] = {}
    for rec in records:
        m = by.setdefault(
            rec.result.model,
            {"model": rec.result.model, "scored": 0, "unscored": 0, **dict.fromkeys(COUNTERS, 0)},
        )
        m["scored" if rec.result.scored else "unscored"] += 1
        for name in COUNTERS:
            m[name] += counter(rec, name)
    return [by[k] for k in sorted(by)]


def _spread(s: Spread) -> dict[str, Any]:
    return {"runs": s.n, "mean": float(s.mean), "sd": s.sd}


def document(
    records: Sequence[Record],
    cells: Sequence[Cell],
    task_spreads: Mapping[tuple[str, str, str], Spread],
    macros: Sequence[Macro],
    macro_spreads: Mapping[tuple[str, str, str], Spread],
    sources: Sequence[Mapping[str, Any]],
    reference: bool,
    marks: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """results.json (schema `SCHEMA` version `SCHEMA_VERSION`; docs/RESULTS.md). `sources`:
    each merged run's `provenance`, the first deciding the top-level one."""
    marks = marks or {}
    counts = model_counts(records)
    for c in counts:
        c["mismatch"] = marks.get(c["model"], "")
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "provenance": {**sources[0], "sources": list(sources)},
        "formulas": FORMULAS,
        "models": counts,
        "episodes": [episode_row(r) for r in records],
        "task_runs": [
            {
                "model": c.model,
                "track": c.track,
                "task": c.task,
                "run": c.run,
                "successes": c.successes,
                "total": c.total,
                "rate": float(c.rate),
            }
            for c in cells
        ],
        "tasks": [
            {"model": m, "track": t, "task": task, **_spread(s)}
            for (m, t, task), s in task_spreads.items()
        ],
        "macro_runs": [
            {
                "model": m.model,
                "track": m.track,
                "run": m.run,
                "subset": m.subset,
                "families": list(m.families),
                "rate": _num(m.rate),
            }
            for m in macros
        ],
        "macro": [
            {"model": m, "track": t, "subset": subset, **_spread(s)}
            for (m, t, subset), s in macro_spreads.items()
        ],
        "reference": {
            "label": P.REFERENCE_LABEL,
            "source": P.SOURCE,
            "overall": {m: {s: list(v) for s, v in P.OVERALL[m].items()} for m in P.MODELS},
            "per_task": {t: {m: list(v) for m, v in P.PER_TASK[t].items()} for t in P.PER_TASK},
        }
        if reference
        else None,
    }


EPISODE_COLUMNS = [
    "model",
    "track",
    "task",
    "run",
    "seed",
    "protocol",
    "status",
    "scored",
    "success",
    "stop_reason",
    "steps_used",
    "step_budget",
    *COUNTERS,
]


def episode_csv_rows(records: Sequence[Record]) -> list[list[Any]]:
    return [[row[c] for c in EPISODE_COLUMNS] for row in map(episode_row, records)]


def sort_key(rec: Record) -> tuple[str, str, str, int, int]:
    r = rec.result
    return (r.model, rec.track, r.task, r.run, r.seed)
