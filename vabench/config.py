"""Sweep configuration: the YAML file `python -m vabench.sweep CONFIG` runs.

    name: my-sweep                 # default: the file's stem
    out: runs/my-sweep             # default: runs/<name>
    models:                        # vabench.llm_pool.config.ModelEndpoint entries
      - {name: local, api: openai_chat, base_url: embedded}   # the sweep's embedded server
      - {name: gpt, api: openai_chat, model: gpt-5, api_key_env: OPENAI_API_KEY,
         prices: {input: 1.25, output: 10.0}}
    embedded_server: {policy: random_action}   # vabench.llm_pool.server.ServerConfig fields
    tracks: [active, passive]      # built-in: active, passive (base suite), transfer (the held-out
                                   # variants of the selected tasks), long_horizon (the basket);
                                   # or {name, protocol, suite, summaries} for an ablation track
    summaries: own                 # every track's default: own | none | shared:<model>
    learning: {demo_cache: .cache/demos, max_model_calls: 30}
    tasks: base                    # the 14 base families, or a list of registered task names
    seeds: verified                # each task's manifest; {verified: N}: its first N; [1000, 1001]:
                                   # these seeds for every task; {task: [seeds]}: per task
    runs: 3
    step_budget: 5                 # optional cap on every task's budget (smoke runs)
    simulator: {backend: auto, impl: auto, lanes: null, window_s: 0.01}  # backend: auto | mjx | c
    render: {backend: auto, width: 1280, height: 960, quality: 95, subsampling: "420",
             workers: 2, platform: auto}   # backend: auto | warp (GPU) | gl
    executor: {kind: auto, address: null, max_tasks: null, max_episodes: 256, in_flight: auto,
               slots_per_task: null}       # kind: auto | local | processes | ray
    retries: {infrastructure_rounds: 3}

`load_config` reads and checks the whole file before anything is called: unknown keys (typos),
wrong types, bad ranges, unknown tasks (with a "did you mean"), unusable seed specs, missing
seed manifests, unset API-key variables, duplicate or path-unsafe model names and unknown
embedded-server policies. Every problem found becomes one line of a single `SweepConfigError`,
`<file>: <dotted field>: <problem>`, so one edit round fixes them all.

Tracks: a track is a camera protocol, a task suite and a summary mode. `active` and `passive`
run the selected `tasks`; `transfer` runs the held-out variants (`<base>_heldout`) of the
selected base families; `long_horizon` runs the basket task. Every track reads summaries learned
from demonstrations (vabench.sweep.summaries): `own` (the model's own, learned once per family
in a learning stage), `shared:<model>` (another model's) or `none`. A custom track such as
`{name: active_none, protocol: active, summaries: none}` runs a summary-source ablation next to
`active` in the same sweep.

The result, `SweepConfig`, is resolved: explicit tracks, task names and the seeds of each task.
`SweepConfig.document()` is a YAML-able mapping of that resolved config (what the sweep writes
to RUN_DIR/sweep.yaml) which `load_config` reads back to an equal config.
"""

from __future__ import annotations

import difflib
import os
import re
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from vabench.llm_pool.config import ApiName, ConfigError, ModelEndpoint
from vabench.llm_pool.policies import POLICIES
from vabench.llm_pool.server import ServerConfig
from vabench.render.images import ImageSettings
from vabench.seeds import verified_seeds
from vabench.tasks import BASE_FAMILIES, REGISTRY, SUITES

Track = Literal["active", "passive"]
"""A camera protocol (also the names of the two built-in base-suite tracks)."""
TRACKS: tuple[str, ...] = typing.get_args(Track)
Suite = Literal["base", "transfer", "long_horizon"]
BUILTIN_TRACKS: dict[str, tuple[Track, Suite]] = {
    "active": ("active", "base"),
    "passive": ("passive", "base"),
    "transfer": ("active", "transfer"),
    "long_horizon": ("active", "long_horizon"),
}
"""Built-in track name -> (camera protocol, task suite)."""
SUMMARY_MODES = ("own", "none", "shared:<model>")

EMBEDDED = "embedded"
"""The `base_url` that means "the embedded server the sweep starts"."""
EMBEDDED_PLACEHOLDER_URL = "http://embedded.invalid"
"""Stands in for the embedded server's address until it runs (`SweepConfig.endpoints`)."""

_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")  # model names become directory names


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SimulatorOptions(_Strict):
    backend: Literal["auto", "mjx", "c"] = "auto"
    """"auto": MuJoCo Warp where a CUDA GPU and the [gpu] extra are present, else C MuJoCo
    (`sim_mjx.backends.resolve`; `--dry-run` says which and why); "mjx": every slot of a task
    in one GPU/TPU batch (impl below); "c": C MuJoCo slot by slot (the fastest path without an
    NVIDIA GPU). See README, "Choosing a physics backend"."""
    impl: Literal["auto", "jax", "warp"] = "auto"
    """mjx only: "warp" (MuJoCo Warp, NVIDIA GPUs; the [gpu] extra), "jax" (MJX on JAX), or
    "auto" (warp where it can run, else jax)."""
    lanes: int | None = Field(default=None, ge=1)
    """Width of the vectorised physics (impl jax only; see `sim_mjx.interface.in_lanes`)."""
    nconmax: int | None = Field(default=None, ge=1)
    """Contacts per slot the GPU buffers hold (impl warp only; default: sized from the scene).
    A slot that overflows ends as an infrastructure error naming this field."""
    njmax: int | None = Field(default=None, ge=1)
    """Constraint rows per slot (impl warp only; default: sized from the scene)."""
    deterministic: bool = False
    """impl warp only: MuJoCo Warp's stable contact and constraint orderings (bit-reproducible
    runs on a GPU, slower)."""
    window_s: float = Field(default=0.01, ge=0)
    """How long the simulator batch waits to gather actions before stepping."""

    def batch_kwargs(self, backend: str, impl: str) -> dict[str, Any]:
        """The TaskBatch arguments these options ask for, on the resolved `backend` and `impl`
        (`sim_mjx.backends.resolve`)."""
        out: dict[str, Any] = {"backend": backend}
        if backend != "mjx":
            return out
        out["impl"] = impl
        if impl == "jax" and self.lanes:
            out["lanes"] = self.lanes
        if impl == "warp":
            extra = {"nconmax": self.nconmax, "njmax": self.njmax}
            out.update({k: v for k, v in extra.items() if v is not None})
            if self.deterministic:
                out["deterministic"] = True
        return out


class RenderOptions(_Strict):
    backend: Literal["auto", "warp", "gl"] = "auto"
    """warp: MuJoCo Warp's batch ray tracer on an NVIDIA GPU (the [gpu] extra); gl: the GL
    worker processes (EGL, or Mesa's llvmpipe without a GPU); auto: warp where it can run,
    else gl (`vabench.render.backends`)."""
    width: int = Field(default=1280, ge=16, le=1280)
    height: int = Field(default=960, ge=16, le=960)
    """Model image size; at most the camera's 1280x960 (FACTS)."""
    quality: int = Field(default=95, ge=1, le=100)
    subsampling: Literal["420", "422", "444"] = "420"
    """JPEG chroma subsampling (libjpeg's default 4:2:0), the same on both backends."""
    workers: int = Field(default=2, ge=1)
    """GL render worker processes per sweep process (backend gl)."""
    platform: Literal["auto", "egl", "osmesa"] = "auto"
    """The GL platform (backend gl)."""

    def image_settings(self) -> ImageSettings:
        return ImageSettings(self.width, self.height, self.quality, self.subsampling)


class ExecutorOptions(_Strict):
    kind: Literal["auto", "local", "processes", "ray"] = "auto"
    """auto: `processes` on a host of 4 or more cores, else `local` (`sweep.choices`; `--dry-run`
    says which and why); local: one process; processes: cells of the plan as worker processes
    of this host, `max_tasks` at once (many cores: C rollouts, CPU-heavy embedded policies);
    ray: cells as Ray tasks over a cluster."""
    address: str | None = None
    """`ray.init(address=...)`; unset starts or joins a local Ray instance (ray only)."""
    max_tasks: int | None = Field(default=None, ge=1)
    """Task batches run at once in one process (local; default 4), or cells at once
    (processes: default one per core; ray: default 4)."""
    max_episodes: int = Field(default=256, ge=1)
    """The most episodes in flight at once in one process (and simulator slots per task
    batch)."""
    in_flight: Literal["auto"] | int = "auto"
    """Episodes in flight in one process: "auto" adapts between 1 and `max_episodes` so that
    the simulator, renderer and model endpoints stay busy without queueing (Little's law,
    `sweep.inflight`); a number holds that many (at most `max_episodes`)."""
    slots_per_task: int | None = Field(default=None, ge=1)
    """Simulator slots of one task batch; default: the task's planned episodes, at most
    `max_episodes`."""

    @field_validator("in_flight", mode="plain")
    @classmethod
    def _in_flight(cls, value: Any) -> Literal["auto"] | int:
        if value == "auto" or (_is_int(value) and value >= 1):
            return value
        raise ValueError(f"expected 'auto' or a whole number >= 1, got {value!r}")

    def slots(self, planned: int) -> int:
        """Simulator slots for a task batch that will run `planned` episodes."""
        if self.slots_per_task is not None:
            return self.slots_per_task
        return max(1, min(planned, self.max_episodes))


class TrackSpec(_Strict):
    """One track: which tasks, under which camera protocol, reading whose summaries."""

    name: str
    protocol: Track = "active"
    suite: Suite = "base"
    summaries: str = "own"
    """own | none | shared:<model> (see the module docstring)."""

    def summary_source(self, model: str) -> str | None:
        """The model whose summaries episodes of `model` read on this track (None: none)."""
        if self.summaries == "none":
            return None
        return model if self.summaries == "own" else self.summaries.removeprefix("shared:")


class LearningOptions(_Strict):
    demo_cache: str = ".cache/demos"
    """Where demonstration videos are cached (built when missing; `python -m vabench.demos`)."""
    max_model_calls: int = Field(default=30, ge=1)
    """Model calls one learning session may use (`agent.learning.LearningLimits`)."""


class RetryOptions(_Strict):
    infrastructure_rounds: int = Field(default=3, ge=0)
    """How many times episodes ended by an infrastructure error are re-run (FACTS: 3)."""


class _SweepFile(_Strict):
    """The document's schema. `tasks` and `seeds` have several spellings and name registry
    entries, so they are checked by `_resolve_tasks` and `_resolve_seeds` instead."""

    name: str | None = Field(default=None, min_length=1)
    out: str | None = Field(default=None, min_length=1)
    models: list[ModelEndpoint] = Field(min_length=1)
    embedded_server: ServerConfig | None = None
    tracks: list[Any] = Field(min_length=1)
    """Checked by `_resolve_tracks`."""
    summaries: str = "own"
    learning: LearningOptions = Field(default_factory=LearningOptions)
    tasks: Any = "base"
    seeds: Any = "verified"
    runs: int = Field(default=3, ge=1)
    step_budget: int | None = Field(default=None, ge=1)
    simulator: SimulatorOptions = Field(default_factory=SimulatorOptions)
    render: RenderOptions = Field(default_factory=RenderOptions)
    executor: ExecutorOptions = Field(default_factory=ExecutorOptions)
    retries: RetryOptions = Field(default_factory=RetryOptions)


class SweepConfig(_Strict):
    """A checked, resolved sweep configuration."""

    name: str
    out: str
    models: tuple[ModelEndpoint, ...]
    """Embedded models carry `EMBEDDED_PLACEHOLDER_URL`; use `endpoints()` to call them."""
    embedded_models: tuple[str, ...] = ()
    """Names of the models served by the embedded server."""
    embedded_server: ServerConfig = Field(default_factory=ServerConfig)
    tracks: tuple[TrackSpec, ...]
    tasks: tuple[str, ...]
    """The selected tasks of base-suite tracks, in the order written (`base`: the paper's
    order); other suites derive theirs (`track_tasks`)."""
    seeds: dict[str, tuple[int, ...]]
    """The seeds of every planned task (`all_tasks`)."""
    learning: LearningOptions = Field(default_factory=LearningOptions)
    runs: int = 3
    step_budget: int | None = None
    simulator: SimulatorOptions = Field(default_factory=SimulatorOptions)
    render: RenderOptions = Field(default_factory=RenderOptions)
    executor: ExecutorOptions = Field(default_factory=ExecutorOptions)
    retries: RetryOptions = Field(default_factory=RetryOptions)

    def model(self, name: str) -> ModelEndpoint:
        for endpoint in self.models:
            if endpoint.name == name:
                return endpoint
        raise KeyError(f"no model {name!r}; models: {[m.name for m in self.models]}")

    def track(self, name: str) -> TrackSpec:
        for track in self.tracks:
            if track.name == name:
                return track
        raise KeyError(f"no track {name!r}; tracks: {[t.name for t in self.tracks]}")

    @property
    def track_names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.tracks)

    def track_tasks(self, track: TrackSpec | str) -> tuple[str, ...]:
        """The tasks a track runs (see the module docstring)."""
        spec = self.track(track) if isinstance(track, str) else track
        return suite_tasks(spec.suite, self.tasks)

    @property
    def all_tasks(self) -> tuple[str, ...]:
        """Every task some track runs, each once, in track then task order."""
        out: dict[str, None] = {}
        for track in self.tracks:
            out.update(dict.fromkeys(self.track_tasks(track)))
        return tuple(out)

    def budget(self, task: str) -> int:
        """The step budget episodes of `task` run with: the task's, capped by `step_budget`."""
        own = REGISTRY[task].step_budget
        return own if self.step_budget is None else min(own, self.step_budget)

    def endpoints(self, embedded_base_url: Callable[[ApiName], str]) -> list[ModelEndpoint]:
        """The endpoints to call, embedded ones pointed at the running server
        (`embedded_base_url` is e.g. `LocalServer.base_url`)."""
        return [
            m.model_copy(update={"base_url": embedded_base_url(m.api)})
            if m.name in self.embedded_models
            else m
            for m in self.models
        ]

    def document(self) -> dict[str, Any]:
        """This config as a YAML-able mapping that `load_config` reads back to an equal config
        (explicit tasks, seeds per task). The embedded server's `api_key` is left out: a
        secret never goes to a run directory."""
        models = []
        for m in self.models:
            entry = m.model_dump(mode="json", exclude_defaults=True)
            if m.name in self.embedded_models:
                entry["base_url"] = EMBEDDED
            models.append(entry)
        doc: dict[str, Any] = {"name": self.name, "out": self.out, "models": models}
        if self.embedded_models:
            doc["embedded_server"] = self.embedded_server.model_dump(
                mode="json", exclude_defaults=True, exclude={"api_key"}
            )
        doc |= {
            "tracks": [t.model_dump(mode="json") for t in self.tracks],
            "tasks": list(self.tasks),
            "seeds": {t: list(s) for t, s in self.seeds.items()},
            "runs": self.runs,
            "step_budget": self.step_budget,
        }
        for key in ("learning", "simulator", "render", "executor", "retries"):
            doc[key] = getattr(self, key).model_dump(mode="json")
        return doc


@dataclass(frozen=True)
class Problem:
    path: str
    """Dotted field path (`models[1].limits.rpm`), or `line L, column C` for YAML syntax."""
    message: str


class SweepConfigError(ValueError):
    """Everything wrong with one config file: one line `<file>: <field>: <problem>` each."""

    def __init__(self, file: str, problems: Iterable[Problem]):
        self.file = file
        self.problems = list(problems)
        lines = [
            f"{file}: {p.path}: {p.message}" if p.path else f"{file}: {p.message}"
            for p in self.problems
        ]
        super().__init__("\n".join(lines))


# -- loading ----------------------------------------------------------------------------------


def load_config(
    path: Path | str,
    *,
    environ: Mapping[str, str] = os.environ,
    overrides: Mapping[str, Any] | None = None,
) -> SweepConfig:
    """Read, check and resolve the sweep config at `path`.

    `overrides` replace values of the document before it is checked; keys are dotted field
    paths (`out`, `executor.kind`), as the command line sets them. `environ` is where the
    models' `api_key_env` variables must be set (and non-empty).

    Raises `SweepConfigError` listing every problem found (see the module docstring).
    """
    path = Path(path)
    file = str(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise SweepConfigError(file, [Problem("", f"cannot read: {err.strerror or err}")]) from None
    try:
        doc = yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader subclass
    except yaml.MarkedYAMLError as err:
        raise SweepConfigError(file, [_yaml_problem(err)]) from None
    except yaml.YAMLError as err:
        raise SweepConfigError(file, [Problem("", f"YAML error: {err}")]) from None
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise SweepConfigError(
            file, [Problem("", f"expected a mapping of settings, got {type(doc).__name__}")]
        )
    doc = _apply_overrides(doc, overrides or {})
    config, problems = _check(doc, path.stem, environ)
    if problems or config is None:
        order = {key: i for i, key in enumerate(doc)}  # report in the order the file reads
        problems.sort(key=lambda p: _position(p.path, order))
        raise SweepConfigError(file, problems)
    return config


def _position(path: str, order: Mapping[str, int]) -> tuple[int, int]:
    """Where a problem's field is in the file: its section, then its list entry."""
    match = re.match(r"([^.\[]*)(?:\[(\d+)\])?", path)
    head, index = (match.group(1), match.group(2)) if match else (path, None)
    return order.get(head, len(order)), -1 if index is None else int(index)


def _check(
    doc: dict[str, Any], stem: str, environ: Mapping[str, str]
) -> tuple[SweepConfig | None, list[Problem]]:
    """Validate the document; every section is checked even when another one fails."""
    problems: list[Problem] = []
    doc, embedded = _mark_embedded(doc)
    parsed: _SweepFile | None = None
    try:
        parsed = _SweepFile.model_validate(doc)
    except ValidationError as err:
        problems += _pydantic_problems(err)
    problems += _model_problems(doc.get("models"), environ)
    problems += _server_problems(doc.get("embedded_server"))
    tasks, task_problems = _resolve_tasks(doc.get("tasks", "base"))
    problems += task_problems
    tracks, track_problems = _resolve_tracks(doc, tasks)
    problems += track_problems
    planned: dict[str, None] = {}
    for track in tracks:
        planned.update(dict.fromkeys(suite_tasks(track.suite, tasks)))
    seeds, seed_problems = _resolve_seeds(doc.get("seeds", "verified"), list(planned))
    if not task_problems and not track_problems:  # else they would only repeat those
        problems += seed_problems
    executor = doc.get("executor")
    if isinstance(executor, dict) and executor.get("address") and executor.get("kind") != "ray":
        problems.append(Problem("executor.address", "only used with kind: ray"))
    if problems or parsed is None:
        return None, problems
    name = parsed.name or stem
    config = SweepConfig(
        name=name,
        out=parsed.out or f"runs/{name}",
        models=tuple(parsed.models),
        embedded_models=tuple(embedded),
        embedded_server=parsed.embedded_server or ServerConfig(),
        tracks=tuple(tracks),
        tasks=tuple(tasks),
        learning=parsed.learning,
        seeds=seeds,
        runs=parsed.runs,
        step_budget=parsed.step_budget,
        simulator=parsed.simulator,
        render=parsed.render,
        executor=parsed.executor,
        retries=parsed.retries,
    )
    return config, []


def _mark_embedded(doc: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """The document with `base_url: embedded` replaced by the placeholder URL, and the names of
    those models (so the endpoint schema checks them like any other)."""
    models = doc.get("models")
    if not isinstance(models, list):
        return doc, []
    out, names = [], []
    for entry in models:
        if isinstance(entry, dict) and entry.get("base_url") == EMBEDDED:
            entry = {**entry, "base_url": EMBEDDED_PLACEHOLDER_URL}
            names.append(str(entry.get("name")))
        out.append(entry)
    return {**doc, "models": out}, names


def _apply_overrides(doc: dict[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    doc = dict(doc)
    for dotted, value in overrides.items():
        *parents, leaf = dotted.split(".")
        node = doc
        for key in parents:
            child = node.get(key)
            node[key] = dict(child) if isinstance(child, dict) else {}
            node = node[key]
        node[leaf] = value
    return doc


# -- the checks pydantic cannot make -----------------------------------------------------------


def _model_problems(models: Any, environ: Mapping[str, str]) -> list[Problem]:
    """Path-safe unique names and set key variables (the schema checks the rest)."""
    if not isinstance(models, list):
        return []
    problems = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(models):
        if not isinstance(entry, dict):
            continue
        name = entry.get("name")
        if isinstance(name, str) and name:
            if not _SAFE_NAME.match(name):
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
        if isinstance(key_env, str) and not environ.get(key_env):
            problems.append(
                Problem(f"models[{i}].api_key_env", f"environment variable {key_env} is not set")
            )
    return problems


def _server_problems(server: Any) -> list[Problem]:
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
            problems.append(Problem(where, _unknown("policy", policy, POLICIES)))
    return problems


def _list_duplicates(values: Any, where: str) -> list[Problem]:
    if not isinstance(values, list):
        return []
    seen: set[Any] = set()
    problems = []
    for i, value in enumerate(values):
        if isinstance(value, str | int) and value in seen:
            problems.append(Problem(f"{where}[{i}]", f"duplicate {value!r}"))
        if isinstance(value, str | int):
            seen.add(value)
    return problems


def suite_tasks(suite: str, selected: Iterable[str]) -> tuple[str, ...]:
    """The registered tasks of `suite` for the selected base-suite tasks: those tasks
    themselves ("base"), the held-out variants of the selected ones ("transfer"), every
    long-horizon family ("long_horizon")."""
    selected = tuple(selected)
    if suite == "base":
        return selected
    if suite == "transfer":
        return tuple(
            n for n in SUITES["transfer"] if n in REGISTRY and REGISTRY[n].base_family in selected
        )
    return tuple(n for n in SUITES[suite] if n in REGISTRY)


def _resolve_tracks(doc: dict[str, Any], tasks: list[str]) -> tuple[list[TrackSpec], list[Problem]]:
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
                    _unknown("track", name, BUILTIN_TRACKS)
                    + " (a custom track is a mapping {name, protocol, suite, summaries})",
                )
            )
            continue
        if not _SAFE_NAME.match(name):
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
                for p in _pydantic_problems(err, TrackSpec)
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
        return [Problem(where, _unknown("model", source, [str(m) for m in models]))]
    return [Problem(where, f"expected one of {', '.join(SUMMARY_MODES)}, got {mode!r}")]


def _resolve_tasks(spec: Any) -> tuple[list[str], list[Problem]]:
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
            problems.append(Problem(f"tasks[{i}]", _unknown("task", name, REGISTRY)))
        elif name in names:
            problems.append(Problem(f"tasks[{i}]", f"duplicate {name!r}"))
        else:
            names.append(name)
    return names, problems


_SEED_FORMS = (
    "'verified', {verified: N}, a list of seeds, or a mapping from task name to a list of seeds"
)


def _resolve_seeds(spec: Any, tasks: list[str]) -> tuple[dict[str, tuple[int, ...]], list[Problem]]:
    """The seeds of each task; see the module docstring for the four spellings."""
    if spec == "verified" or (isinstance(spec, dict) and set(spec) == {"verified"}):
        n = None if spec == "verified" else spec["verified"]
        if n is not None and (not _is_int(n) or n < 1):
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
                problems.append(Problem(where, _unknown("planned task", str(task), tasks)))
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
        if not _is_int(seed) or seed < 0:
            problems.append(
                Problem(f"{where}[{i}]", f"expected a seed (integer >= 0), got {seed!r}")
            )
        elif seeds.index(seed) != i:
            problems.append(Problem(f"{where}[{i}]", f"duplicate seed {seed}"))
    return problems


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _unknown(kind: str, name: str, valid: Iterable[str]) -> str:
    valid = list(valid)
    close = difflib.get_close_matches(name, valid, n=1)
    if close:
        return f"unknown {kind} {name!r}; did you mean {close[0]!r}?"
    return f"unknown {kind} {name!r}; valid: {', '.join(valid)}"


# -- turning pydantic and YAML errors into problems --------------------------------------------


def _pydantic_problems(
    err: ValidationError, schema: type[BaseModel] | None = None
) -> list[Problem]:
    problems = []
    for e in err.errors():
        loc = tuple(e["loc"])
        ctx_error = e.get("ctx", {}).get("error")
        if isinstance(ctx_error, ConfigError):  # raised inside an endpoint validator
            problems.append(
                Problem(_dotted(loc + tuple(ctx_error.field.split("."))), ctx_error.message)
            )
            continue
        message = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            message = _unknown("field", str(loc[-1]), _field_names(schema or _SweepFile, loc[:-1]))
        elif e["type"] not in ("missing", "value_error") and "input" in e:
            message += f", got {_short(e['input'])}"
        problems.append(Problem(_dotted(loc), message))
    return problems


def _dotted(loc: Iterable[Any]) -> str:
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _field_names(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    """The field names of the pydantic model found at `loc` under `model` (for suggestions)."""
    node: Any = model
    for part in loc:
        if isinstance(part, int):
            node = _inner(node, list)
            continue
        if not (isinstance(node, type) and issubclass(node, BaseModel)):
            node = _inner(node, dict)
            continue
        field = node.model_fields.get(part)
        if field is None:
            return []
        node = _unwrap(field.annotation)
    return list(node.model_fields) if isinstance(node, type) and issubclass(node, BaseModel) else []


def _unwrap(annotation: Any) -> Any:
    """`X | None` -> X."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return args[0] if len(args) == 1 else annotation
    return annotation


def _inner(annotation: Any, container: type) -> Any:
    """The item type of list[X] (or the value type of dict[K, X])."""
    args = typing.get_args(_unwrap(annotation))
    return (
        _unwrap(args[-1]) if typing.get_origin(_unwrap(annotation)) is container and args else None
    )


def _yaml_problem(err: yaml.MarkedYAMLError) -> Problem:
    mark = err.problem_mark or err.context_mark
    where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
    what = " ".join(s for s in (err.context, err.problem) if s)
    return Problem(where, f"YAML syntax error: {what}")


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader that rejects a key written twice in one mapping (PyYAML keeps the last one
    silently, so a repeated `runs:` would hide the first)."""


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict[Any, Any]:
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                "while reading a mapping",
                node.start_mark,
                f"duplicate key {key!r}",
                key_node.start_mark,
            )
        seen.add(key)
    return loader.construct_mapping(node)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
