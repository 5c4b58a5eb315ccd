"""The checks pydantic cannot make, and the resolution of tracks, tasks and seeds.

Names must be path-safe and unique, key variables set, policies registered; `tasks` and
`seeds` have several spellings (`vabench.config` docstring) and become, per task, the tuple of
seeds the sweep plans. Each function returns what it resolved and the `Problem`s it found, so
one pass reports everything.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import ValidationError

from vabench.config.problems import Problem, is_int, pydantic_problems, unknown
from vabench.config.schema import BUILTIN_TRACKS, SAFE_NAME, SUMMARY_MODES, TrackSpec, suite_tasks
from vabench.llm_pool.policies import POLICIES
from vabench.tasks import BASE_FAMILIES, REGISTRY
from vabench.tasks.manifests import verified_seeds


def model_problems(models: Any, environ: Mapping[str, str] | None) -> list[Problem]:
    """Path-safe unique names and set key variables (the schema checks the rest; keys not
    without an `environ`)."""
    if not isinstance(models, list):
        return []
    problems = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(models):
        if not isinstance(entry, dict):
            continue
        name = entry.get("name")
        if isinstance(name, str) and name:
            if not SAFE_NAME.match(name):
                problems.append(
                    Problem(
                        f"models[{i}].name",
                        f"{name!r} names a directory: use letters, digits, '.', '_' and '-' "
                        "(put the provider's id in `model:`)",
                    )
                )
            if name in seen:
                problems.append(
                    Problem(f"models[{i}].name", f"duplicate of models[{seen[name]}] ({name!r})")
                )
            seen.setdefault(name, i)
        key_env = entry.get("api_key_env")
        if environ is not None and isinstance(key_env, str) and not environ.get(key_env):
            problems.append(
                Problem(f"models[{i}].api_key_env", f"environment variable {key_env} is not set")
            )
    return problems


def server_problems(server: Any) -> list[Problem]:
    """Policy names of the embedded server must be registered."""
    if not isinstance(server, dict):
        return []
    problems = []
    named = [("embedded_server.policy", server.get("policy"))]
    per_model = server.get("model_policies")
    if isinstance(per_model, dict):
        named += [
            (f"embedded_server.model_policies.{k}.policy", v.get("policy"))
            for k, v in per_model.items()
            if isinstance(v, dict)
        ]
    for where, policy in named:
        if isinstance(policy, str) and policy not in POLICIES:
            problems.append(Problem(where, unknown("policy", policy, POLICIES)))
    return problems


def resolve_tracks(doc: dict[str, Any], tasks: list[str]) -> tuple[list[TrackSpec], list[Problem]]:
    """`tracks:` entries (a built-in name or a mapping) with the default summary mode filled in;
    every track must plan at least one task and name a usable summary mode."""
    entries, default = doc.get("tracks"), doc.get("summaries", "own")
    if not isinstance(entries, list):
        return [], []  # the schema reports it
    models = [m.get("name") for m in doc.get("models") or [] if isinstance(m, dict)]
    problems: list[Problem] = []
    default_ok = isinstance(default, str)  # else the schema reports it
    if default_ok:
        default_problems = _mode_problems(default, "summaries", models)
        problems += default_problems
        default_ok = not default_problems
    tracks: list[TrackSpec] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(entries):
        where = f"tracks[{i}]"
        if isinstance(entry, str):
            entry = {"name": entry}
        if not isinstance(entry, dict):
            problems.append(Problem(where, f"expected a track name or a mapping, got {entry!r}"))
            continue
        name = entry.get("name")
        if not isinstance(name, str):
            problems.append(Problem(where, f"a track mapping needs a name, got {name!r}"))
            continue
        if len(entry) == 1 and name not in BUILTIN_TRACKS:
            problems.append(
                Problem(
                    where,
                    unknown("track", name, BUILTIN_TRACKS)
                    + " (a custom track is a mapping {name, protocol, suite, summaries})",
                )
            )
            continue
        if not SAFE_NAME.match(name):
            problems.append(
                Problem(
                    f"{where}.name",
                    f"{name!r} names a directory: use letters, digits, '.', '_' and '-'",
                )
            )
            continue
        if name in seen:
            problems.append(Problem(where, f"duplicate track {name!r} (tracks[{seen[name]}])"))
            continue
        seen[name] = i
        fields = dict(entry)
        if name in BUILTIN_TRACKS:
            protocol, suite = BUILTIN_TRACKS[name]
            for key, value in (("protocol", protocol), ("suite", suite)):
                if fields.setdefault(key, value) != value:
                    problems.append(
                        Problem(
                            f"{where}.{key}",
                            f"the built-in track {name!r} has {key} {value!r}; give another "
                            "name to a track with a different one",
                        )
                    )
        mode = fields.setdefault("summaries", default if default_ok else "own")
        if "summaries" in entry and isinstance(mode, str):
            problems += _mode_problems(mode, f"{where}.summaries", models)
        try:
            track = TrackSpec.model_validate(fields)
        except ValidationError as err:
            problems += [
                Problem(f"{where}.{p.path}" if p.path else where, p.message)
                for p in pydantic_problems(err, TrackSpec)
            ]
            continue
        if tasks and not suite_tasks(track.suite, tasks):  # no tasks: `tasks` is reported
            why = (
                "none of the selected tasks has a registered held-out variant"
                if track.suite == "transfer"
                else "no task of the suite is registered"
            )
            problems.append(
                Problem(where, f"track {name!r} (suite {track.suite}) has no task: {why}")
            )
        tracks.append(track)
    return tracks, problems


def _mode_problems(mode: str, where: str, models: list[Any]) -> list[Problem]:
    if mode in ("own", "none"):
        return []
    if mode.startswith("shared:"):
        source = mode.removeprefix("shared:")
        if source in models:
            return []
        return [Problem(where, unknown("model", source, [str(m) for m in models]))]
    return [Problem(where, f"expected one of {', '.join(SUMMARY_MODES)}, got {mode!r}")]


def resolve_tasks(spec: Any) -> tuple[list[str], list[Problem]]:
    """`base` (the base families present, in the paper's order) or a list of task names."""
    if spec == "base":
        return [n for n in BASE_FAMILIES if n in REGISTRY], []
    if not isinstance(spec, list) or not spec:
        return [], [
            Problem("tasks", f"expected 'base' or a non-empty list of task names, got {spec!r}")
        ]
    names: list[str] = []
    problems = []
    for i, name in enumerate(spec):
        if not isinstance(name, str):
            problems.append(Problem(f"tasks[{i}]", f"expected a task name, got {name!r}"))
        elif name not in REGISTRY:
            problems.append(Problem(f"tasks[{i}]", unknown("task", name, REGISTRY)))
        elif name in names:
            problems.append(Problem(f"tasks[{i}]", f"duplicate {name!r}"))
        else:
            names.append(name)
    return names, problems


_SEED_FORMS = (
    "'verified', {verified: N}, a list of seeds, or a mapping from task name to a list of seeds"
)


def resolve_seeds(spec: Any, tasks: list[str]) -> tuple[dict[str, tuple[int, ...]], list[Problem]]:
    """The seeds of each task; see the module docstring for the four spellings."""
    if spec == "verified" or (isinstance(spec, dict) and set(spec) == {"verified"}):
        n = None if spec == "verified" else spec["verified"]
        if n is not None and (not is_int(n) or n < 1):
            return {}, [Problem("seeds.verified", f"expected a whole number >= 1, got {n!r}")]
        return _verified(tasks, n)
    if isinstance(spec, list):
        problems = _seed_list_problems(spec, "seeds")
        return ({t: tuple(spec) for t in tasks}, problems)
    if isinstance(spec, dict) and spec:
        seeds: dict[str, tuple[int, ...]] = {}
        problems = []
        for task, listed in spec.items():
            where = f"seeds.{task}"
            if task not in tasks:
                problems.append(Problem(where, unknown("planned task", str(task), tasks)))
            elif not isinstance(listed, list) or not listed:
                problems.append(
                    Problem(where, f"expected a non-empty list of seeds, got {listed!r}")
                )
            else:
                problems += _seed_list_problems(listed, where)
                seeds[task] = tuple(listed)
        problems += [Problem("seeds", f"no seeds for task {t!r}") for t in tasks if t not in spec]
        return {t: seeds[t] for t in tasks if t in seeds}, problems
    return {}, [Problem("seeds", f"expected {_SEED_FORMS}, got {spec!r}")]


def _verified(tasks: list[str], n: int | None) -> tuple[dict[str, tuple[int, ...]], list[Problem]]:
    seeds: dict[str, tuple[int, ...]] = {}
    problems = []
    for task in tasks:
        try:
            retained = verified_seeds(task)
        except (FileNotFoundError, ValueError) as err:
            problems.append(Problem("seeds", f"task {task!r}: {err}"))
            continue
        if n is not None and len(retained) < n:
            problems.append(
                Problem("seeds.verified", f"task {task!r} has only {len(retained)} verified seeds")
            )
        seeds[task] = tuple(retained if n is None else retained[:n])
    return seeds, problems


def _seed_list_problems(seeds: list[Any], where: str) -> list[Problem]:
    if not seeds:
        return [Problem(where, "expected at least one seed")]
    problems = []
    for i, seed in enumerate(seeds):
        if not is_int(seed) or seed < 0:
            problems.append(
                Problem(f"{where}[{i}]", f"expected a seed (integer >= 0), got {seed!r}")
            )
        elif seeds.index(seed) != i:
            problems.append(Problem(f"{where}[{i}]", f"duplicate seed {seed}"))
    return problems
