"""Which sweep a run directory belongs to: RUN_DIR/plan.json, written once, checked on resume.

Resumed with a config whose plan differs, a run directory would mix two sweeps in one table (a
changed `step_budget` keeps every episode id), so the first run stores the plan's identity
(`plan_identity`, the episode ids) and every later run compares it, naming the differing fields.
The rest (executor, limits, keys, `VABENCH_*` switches) may change; plan.json keeps each
invocation's switches, so the run directory says how its episodes were run.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import yaml

from vabench import switches
from vabench.config import SweepConfig
from vabench.protocol.version import PROTOCOL_VERSION
from vabench.run_layout import RunDir
from vabench.sweep.plan import EpisodeKey

PLAN_VERSION = 2
PLAN_FIELDS = ("models", "tracks", "tasks", "seeds", "runs", "step_budget", "protocol_version")
"""The config fields that decide the episodes and their outcomes. Of a model only what changes
its answers (`_MODEL_FIELDS`; of an embedded server's model its policy too), so a run resumes
with a new key or limits; the protocol's version too: another protocol, another measurement."""
_MODEL_FIELDS = ("name", "api", "model", "generation")


class RunDirMismatch(ValueError):
    """The run directory was made by a plan that differs from the config's; names the fields."""


def plan_identity(config: SweepConfig) -> dict[str, Any]:
    """The values of `PLAN_FIELDS` that decide `config`'s plan (JSON-ready)."""
    doc = config.document()
    server = doc.get("embedded_server", {})
    models = []
    for m in config.models:
        entry = m.model_dump(mode="json", include=set(_MODEL_FIELDS), exclude_none=True)
        entry["model"] = m.provider_model
        entry["generation"] = m.generation.model_dump(mode="json", exclude_none=True)
        if m.name in config.embedded_models:
            policy = server.get("model_policies", {}).get(m.provider_model)
            entry["embedded_policy"] = policy or {
                "policy": server.get("policy", "random_action"),
                "options": server.get("policy_options", {}),
            }
        models.append(entry)
    return {
        "models": models,
        "tracks": doc["tracks"],
        "tasks": doc["tasks"],
        "seeds": doc["seeds"],
        "runs": doc["runs"],
        "step_budget": doc["step_budget"],
        "protocol_version": PROTOCOL_VERSION,
    }


def _short(value: Any) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 80 else text[:77] + "..."


def differing_fields(before: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """One line per plan field whose value differs: `field: before -> now` (models by name)."""
    lines = []
    for name in PLAN_FIELDS:
        a, b = before.get(name), now.get(name)
        if a == b:
            continue
        if name == "models" and isinstance(a, list) and isinstance(b, list):
            old = {m.get("name"): m for m in a}
            new = {m.get("name"): m for m in b}
            for model in sorted(old.keys() | new.keys(), key=str):
                if old.get(model) != new.get(model):
                    lines.append(
                        f"models[{model}]: {_short(old.get(model))} -> {_short(new.get(model))}"
                    )
            continue
        lines.append(f"{name}: {_short(a)} -> {_short(b)}")
    return lines


def run_dir_problem(run_dir: Path, config: SweepConfig, keys: list[EpisodeKey]) -> str | None:
    """Why `run_dir` cannot hold this plan (None: it can), reading only (`--dry-run` too): it is
    a file, cannot be made or written, or another plan made it (the differing fields named)."""
    if run_dir.exists() and not run_dir.is_dir():
        return f"the run directory {run_dir} is a file; name a directory with --out DIR"
    existing = next(p for p in (run_dir, *run_dir.parents) if p.exists())
    if not existing.is_dir():
        return f"the run directory {run_dir} cannot be made: {existing} is a file"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"the run directory {run_dir} cannot be written: {existing} is not writable"
    path = RunDir(run_dir).plan
    if not path.exists():
        return None
    ids = [k.as_id() for k in keys]
    before = json.loads(path.read_text(encoding="utf-8"))
    if isinstance(before, list):  # version 1: ids only
        diff = [] if before == ids else [f"episodes: {len(before)} -> {len(ids)}"]
    else:
        diff = differing_fields(before.get("fields", {}), plan_identity(config))
        if not diff and before.get("episodes") != ids:
            diff = [f"episodes: {len(before.get('episodes', []))} -> {len(ids)}"]
    return _refusal(run_dir, diff) if diff else None


def check_run_dir(
    run_dir: Path, config: SweepConfig, keys: list[EpisodeKey], config_dump: dict[str, Any]
) -> None:
    """Store the plan's identity in a new run directory, or refuse one it cannot use
    (`RunDirMismatch`, with `run_dir_problem`'s message); then write the resolved config."""
    problem = run_dir_problem(run_dir, config, keys)
    if problem is not None:
        raise RunDirMismatch(problem)
    files = RunDir(run_dir)
    path = files.plan
    now = switches.resolve(config.switch_values()).values
    before = json.loads(path.read_text(encoding="utf-8")) if path.exists() else None
    if isinstance(before, dict):
        if before.get("switches") != now:
            record = {**before, "switches": now}
            if "switches" in before:  # a plan.json written before switches were kept has none
                record["earlier_switches"] = [
                    *before.get("earlier_switches", []),
                    before["switches"],
                ]
            _write_plan(path, record)
    else:  # a new run directory, or a plan.json of version 1 upgraded in place
        run_dir.mkdir(parents=True, exist_ok=True)
        ids = [k.as_id() for k in keys]
        fields = plan_identity(config)
        _write_plan(path, {"v": PLAN_VERSION, "fields": fields, "episodes": ids, "switches": now})
    files.config.write_text(yaml.safe_dump(config_dump, sort_keys=False), encoding="utf-8")


def _write_plan(path: Path, record: dict[str, Any]) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record), encoding="utf-8")
    tmp.replace(path)


def _refusal(run_dir: Path, diff: list[str]) -> str:
    lines = "\n".join(f"  {line}" for line in diff)
    return (
        f"{run_dir} holds a sweep with a different plan; resuming it would mix the episodes "
        f"of two sweeps in one table. Differing fields (run directory -> this config):\n"
        f"{lines}\n"
        "Restore the config that made it, or start a new run directory with --out DIR."
    )


DISK_RESERVE_BYTES = 200e6
"""Free disk below which the sweep stops (every recorded episode whole): a few episodes'
frames and the report fit in it."""


def disk_short(run_dir: Path, reserve: float | None = None) -> str | None:
    """Why the sweep must stop before its disk is full (None while there is room)."""
    reserve = DISK_RESERVE_BYTES if reserve is None else reserve
    try:
        free = shutil.disk_usage(run_dir).free
    except OSError:
        return None
    if free >= reserve:
        return None
    return (
        f"disk: {free / 1e6:.0f} MB free where {run_dir} lies, below the {reserve / 1e6:.0f} MB "
        "the sweep keeps; every recorded episode is kept: free space (or set records.frames: "
        "failed), then run the same command to resume"
    )
