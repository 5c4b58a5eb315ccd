"""The schema of a sweep config and the resolved `SweepConfig` the sweep runs from.

The sections a file may hold (`simulator`, `render`, `executor`, ...) are pydantic models with
every field documented; `SweepConfig` is the checked, resolved result (`vabench.config.load`).
"""

from __future__ import annotations

import re
import typing
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from vabench.config.problems import is_int
from vabench.llm_pool.config import ApiName, ModelEndpoint
from vabench.llm_pool.server_config import ServerConfig
from vabench.llm_pool.spend import EMBEDDED_BASE_URL, Pricing, pricing_of
from vabench.render.images import ImageSettings
from vabench.sim_mjx.backends import Physics
from vabench.switches import BY_FIELD, DEVICE, SWITCHES
from vabench.tasks import REGISTRY, SUITES

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


SUMMARY_MODES = ("own", "none", "shared:<model>")

EMBEDDED = EMBEDDED_BASE_URL
"""The `base_url` that means "the embedded server the sweep starts"."""
EMBEDDED_PLACEHOLDER_URL = "http://embedded.invalid"
"""Stands in for the embedded server's address until it runs (`SweepConfig.endpoints`)."""

SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
"""Model and track names become directory names."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SimulatorOptions(_Strict):
    backend: Literal["auto", "warp", "mjx", "c"] = "auto"
    """"auto": MuJoCo Warp where a CUDA GPU and the [gpu] extra are present, else C MuJoCo
    (`sim_mjx.backends.resolve`; `--dry-run` says which and why); "warp": MuJoCo Warp, every
    slot of a task in one CUDA graph per action (NVIDIA GPUs; the [gpu] extra); "mjx": MJX on
    JAX, every slot in one JAX batch (TPUs; CPU JAX for tests); "c": C MuJoCo slot by slot (the
    fastest path without an NVIDIA GPU). The names are `sim_mjx.backends.BACKENDS`; the old
    spelling `backend: mjx, impl: warp | jax` is read as warp | mjx, with a warning
    (`config.load`). See README, "Choosing a physics backend"."""
    lanes: int | None = Field(default=None, ge=1)
    """Width of the vectorised physics (backend mjx only; see `sim_mjx.interface.in_lanes`)."""
    nconmax: int | None = Field(default=None, ge=1)
    """Contacts per slot the GPU buffers hold (backend warp only; default: sized from the
    scene). A slot that overflows ends as an infrastructure error naming this field."""
    njmax: int | None = Field(default=None, ge=1)
    """Constraint rows per slot (backend warp only; default: sized from the scene)."""
    deterministic: bool = False
    """backend warp only: MuJoCo Warp's stable contact and constraint orderings
    (bit-reproducible runs on a GPU, slower)."""
    window_s: float = Field(default=0.01, ge=0)
    """How long the simulator batch waits to gather actions before stepping."""
    action_end: Literal["fixed", "at_rest", "paced"] = "fixed"
    """How long an action's physics runs (backends c and warp; mjx always fixed): fixed, 0.8 s
    of substeps for every action; at_rest, each slot's action ends at the first substep after
    its references are final where every joint is at rest, 0.8 s at the latest; paced, as
    at_rest with each move's time following its length (minimum-jerk at the longest move's
    peak acceleration; `sim_mjx.controller.ACTION_ENDS`)."""
    warp_device: str = Field(default="cuda:0", pattern=DEVICE.pattern)
    """The Warp device of the physics and the Warp renderer: "cuda" or "cuda:N" (a worker
    process given one of several GPUs sees it as cuda:0), or "cpu", Warp's CPU device (slow;
    for tests). `VABENCH_WARP_DEVICE` overrides it, as the variables named below do their field
    (`vabench.switches`)."""
    warp_loop: Literal["device", "per_step", "unrolled"] = "device"
    """How a Warp action's CUDA graphs hold its substeps (`sim_mjx.warp.graphs.LOOPS`):
    device, one graph whose substeps run in a CUDA while loop; per_step, a graph per substep;
    unrolled, every substep in one graph (`VABENCH_WARP_LOOP`)."""
    cuda_sync: Literal["block", "spin"] = "block"
    """How threads wait for the GPU (`sim_mjx.warp.cuda_sync`): block, they sleep on events
    made with CU_EVENT_BLOCKING_SYNC; spin, CUDA's default, a core busy per waiting thread
    (`VABENCH_CUDA_SYNC`)."""
    matmul_precision: Literal[
        "highest", "high", "default", "float32", "tensorfloat32", "bfloat16"
    ] = "highest"
    """JAX's float32 matmul precision (`sim_mjx.jax_setup`): contact dynamics and the IK need
    full float32 products; "default" restores JAX's, TF32 on recent NVIDIA GPUs
    (`VABENCH_MATMUL_PRECISION`)."""
    jax_cache: str | None = Field(default=None, min_length=1)
    """JAX's persistent compilation cache: a folder, or "off" (default
    `~/.cache/vabench/jax`; `VABENCH_JAX_CACHE`)."""
    state_cache: str | None = Field(default=None, min_length=1)
    """The cache of settled reset states (`sim_mjx.reset_cache`): a folder, or "off" (default
    `~/.cache/vabench/settled`; `VABENCH_STATE_CACHE`)."""

    def batch_kwargs(self, physics: Physics, critical_path: bool = False) -> dict[str, Any]:
        """The TaskBatch arguments these options ask for, on the resolved `physics`
        (`sim_mjx.backends.resolve`); `critical_path`: the task bounds the sweep's wall time
        (Warp gives its GPU work the highest stream priority)."""
        out: dict[str, Any] = {"backend": physics.value}
        if physics is Physics.MJX_JAX and self.lanes:
            out["lanes"] = self.lanes
        if physics in (Physics.C, Physics.WARP) and self.action_end != "fixed":
            out["action_end"] = self.action_end
        if physics is Physics.WARP:
            extra = {"nconmax": self.nconmax, "njmax": self.njmax}
            out.update({k: v for k, v in extra.items() if v is not None})
            if self.deterministic:
                out["deterministic"] = True
            if critical_path:
                out["critical_path"] = True
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
    warp_jpeg: Literal["auto", "kernels", "nvjpeg", "device", "host"] = "auto"
    """How the Warp renderer encodes its JPEGs (`render.warp_renderer.JPEG_CHOICES`): auto, on
    a GPU its own JPEG kernels, else nvJPEG, else nvImageCodec, else CPU threads (on the CPU,
    threads); kernels; nvjpeg; device (nvImageCodec); host (threads) (`VABENCH_WARP_JPEG`)."""
    concurrency: int = Field(default=1, ge=1)
    """Render requests of one task an engine sends to the Warp renderer side by side; with
    more than one, a pass's frames are copied on the device and the pass is free for the next
    request while they are encoded (`VABENCH_RENDER_CONCURRENCY`)."""

    def image_settings(self) -> ImageSettings:
        return ImageSettings(self.width, self.height, self.quality, self.subsampling)


class ExecutorOptions(_Strict):
    kind: Literal["auto", "local", "processes", "ray"] = "auto"
    """auto: with MuJoCo Warp, `processes` of 4 engine processes per GPU under CUDA MPS
    (`mps`), or without MPS `local` on one GPU (every task batch in one process) and one
    engine process per GPU on several; else `processes` on a host of 4 or more cores, else
    `local` (`config.choices`;
    `--dry-run` says which and why); local: one process; processes: cells of the plan as
    worker processes of this host, `max_tasks` at once (many cores: C rollouts, CPU-heavy
    embedded policies);
    ray: engine actors over a Ray cluster, 4 per GPU under CUDA MPS (README, "Multi-machine
    sweeps")."""
    address: str | None = None
    """`ray.init(address=...)`: "auto" (the cluster this node belongs to) or "HOST:PORT" (its
    head); unset starts or joins a local Ray instance (ray only). Ray Client ("ray://") is
    refused: it does not carry the streamed calls the engines report through."""
    actors: int | None = Field(default=None, ge=1)
    """Engine actors of a Ray sweep (ray only); default when the physics runs on GPUs: 4 per GPU
    of the cluster sharing it under CUDA MPS (`mps: auto` and NVIDIA's control program on the
    driver's node; else one per GPU), else one per `1 + render.workers` CPUs of the cluster."""
    max_tasks: int | None = Field(default=None, ge=1)
    """Task batches run at once in one process (local; default 4), cells at once (processes:
    default one per core; with `auto` on GPUs, engine processes), or chunks at once in one
    engine actor (ray: default 16)."""
    mps: Literal["auto", "off"] = "auto"
    """auto: where several engine processes share a GPU (`auto` with MuJoCo Warp, when NVIDIA's
    `nvidia-cuda-mps-control` is installed: 4 per GPU; on Ray, `actors` above the GPUs), the
    sweep runs a CUDA MPS daemon of its own for them (on Ray one a node), so that their kernels
    run side by side (`tuning.mps`); off: never (one engine process per GPU with `auto`)."""
    max_episodes: int = Field(default=256, ge=1)
    """The most episodes in flight at once in one process (and simulator slots per task
    batch); where engine processes share a GPU under MPS, on that GPU (each of its processes
    keeps its share)."""
    in_flight: Literal["auto"] | int = "auto"
    """Episodes in flight in one process: "auto" adapts between 1 and `max_episodes` so that
    the simulator, renderer and model endpoints stay busy without queueing (Little's law,
    `tuning.inflight`); a number holds that many (at most `max_episodes`)."""
    slots_per_task: int | None = Field(default=None, ge=1)
    """Simulator slots of one task batch; default: the task's planned episodes, at most
    `max_episodes`."""
    precompile: Literal["on", "off", "first"] = "on"
    """Warp physics on a GPU: on, every family's kernels are compiled side by side in the
    background when the sweep starts (once per code and machine), each family's episodes
    starting as soon as its own are in (`tuning.precompile`); off, each family compiles on
    first use; first, every family waits for the whole compile (`VABENCH_WARP_PRECOMPILE`)."""
    cache_dir: str | None = Field(default=None, min_length=1)
    """Where the precompile keeps its markers, under `warp_compiled/` (default
    `~/.cache/vabench`; `VABENCH_CACHE`)."""

    @field_validator("in_flight", mode="plain")
    @classmethod
    def _in_flight(cls, value: Any) -> Literal["auto"] | int:
        if value == "auto" or (is_int(value) and value >= 1):
            return value
        raise ValueError(f"expected 'auto' or a whole number >= 1, got {value!r}")

    def slots(self, planned: int) -> int:
        """Simulator slots for a task batch that will run `planned` episodes."""
        if self.slots_per_task is not None:
            return self.slots_per_task
        return max(1, min(planned, self.max_episodes))


class ProfilingOptions(_Strict):
    """What the sweep measures of itself beside its episodes; a profiled run is not a timing
    run."""

    hostload_s: float = Field(default=60.0, ge=0, allow_inf_nan=False)
    """Seconds between the sweep's "host:" log lines (`tuning.hostload`); 0 turns them off
    (`VABENCH_HOSTLOAD_S`)."""
    cprofile_dir: str | None = Field(default=None, min_length=1)
    """A folder where each worker of `executor: processes` writes a cProfile of each chunk
    (`VABENCH_PROFILE_DIR`)."""
    kernel_dir: str | None = Field(default=None, min_length=1)
    """A folder where each worker of `executor: processes` writes a window of its GPU kernels
    (`tuning.kernel_profile`; `VABENCH_KERNEL_PROFILE`)."""
    kernel_at_s: float = Field(default=60.0, ge=0, allow_inf_nan=False)
    """When the kernel window starts, in seconds after the worker's chunk
    (`VABENCH_KERNEL_PROFILE_AT`)."""
    kernel_s: float = Field(default=20.0, gt=0, allow_inf_nan=False)
    """How long the kernel window lasts, in seconds (`VABENCH_KERNEL_PROFILE_S`)."""
    precompile_stats: str | None = Field(default=None, min_length=1)
    """A folder where each child of the precompile writes what it compiled (default: a
    temporary folder; `VABENCH_PRECOMPILE_STATS`)."""


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
    demo_cache: str | None = None
    """Where demonstration videos are cached (built when missing; `python -m vabench.demos`):
    a folder, or none for the user's cache (`~/.cache/vabench/demos`, under `XDG_CACHE_HOME`
    where set), which every sweep and Ray engine of the machine shares."""
    max_model_calls: int = Field(default=20, ge=1)
    """Model calls one learning session may use (`agent.learning.LearningLimits`; 20, the
    reference's one learning decision)."""

    def cache_path(self) -> Path:
        """The folder `demo_cache` names (`demos.store.default_cache` for none)."""
        from vabench.demos.store import default_cache  # the simulator's constants: lazily

        return Path(self.demo_cache) if self.demo_cache else default_cache()


class RecordOptions(_Strict):
    frames: Literal["all", "failed", "none"] = "all"
    """The images the model saw, kept under each episode's `frames/` (about 6 MB an episode
    at 1280x960): `all`, those of the episodes that `failed` (a success's are removed once its
    result is written), or `none`. Events and results are always kept; the viewer says which
    frames a run kept."""


class RetryOptions(_Strict):
    infrastructure_rounds: int = Field(default=3, ge=0)
    """How many times episodes ended by an infrastructure error are re-run (FACTS: 3)."""


class SweepLimits(_Strict):
    max_cost_usd: float | None = Field(default=None, gt=0)
    """US dollars the whole sweep may spend (its run directory, resumes included): no call is
    sent that could cross it, and the sweep stops saying so (`llm_pool.spend.SpendCaps`).
    Every model not of the embedded server needs `prices`. Each model may have its own too
    (`models[i].limits.max_cost_usd`)."""


class ReportOptions(_Strict):
    reference: bool = True
    """Show the paper's published scores as greyed reference rows beside the run's
    (`vabench.report.published`); false leaves them out."""


class SweepFile(_Strict):
    """The document's schema. `tasks` and `seeds` have several spellings and name registry
    entries, so they are checked by `resolve.resolve_tasks` and `resolve.resolve_seeds`
    instead."""

    name: str | None = Field(default=None, min_length=1)
    out: str | None = Field(default=None, min_length=1)
    models: list[ModelEndpoint] = Field(min_length=1)
    embedded_server: ServerConfig | None = None
    tracks: list[Any] = Field(min_length=1)
    """Checked by `resolve.resolve_tracks`."""
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
    limits: SweepLimits = Field(default_factory=SweepLimits)
    report: ReportOptions = Field(default_factory=ReportOptions)
    records: RecordOptions = Field(default_factory=RecordOptions)
    profiling: ProfilingOptions = Field(default_factory=ProfilingOptions)


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
    limits: SweepLimits = Field(default_factory=SweepLimits)
    report: ReportOptions = Field(default_factory=ReportOptions)
    records: RecordOptions = Field(default_factory=RecordOptions)
    profiling: ProfilingOptions = Field(default_factory=ProfilingOptions)

    def switch_values(self) -> dict[str, Any]:
        """The values of the fields that environment variables may override, by switch name
        (`vabench.switches.BY_FIELD`)."""
        out = {}
        for path, switch in BY_FIELD.items():
            section, leaf = path.split(".")
            out[switch.name] = getattr(getattr(self, section), leaf)
        return out

    def with_switch_values(self, values: dict[str, Any]) -> SweepConfig:
        """This config with the switch fields of `values` (by switch name) set, each section
        validated again; raises pydantic's ValidationError for a value its field refuses."""
        sections: dict[str, dict[str, Any]] = {}
        for name, value in values.items():
            section, leaf = str(SWITCHES[name].field).split(".")
            sections.setdefault(section, {})[leaf] = value
        update = {
            section: type(getattr(self, section)).model_validate(
                {**getattr(self, section).model_dump(), **fields}
            )
            for section, fields in sections.items()
        }
        return self.model_copy(update=update)

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

    def pricing(self) -> dict[str, Pricing]:
        """How each model's cost is shown (`llm_pool.spend.pricing_of`), by name."""
        return {m.name: pricing_of(m.prices, m.name in self.embedded_models) for m in self.models}

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
        for key in (
            "learning",
            "simulator",
            "render",
            "executor",
            "retries",
            "limits",
            "report",
            "records",
            "profiling",
        ):
            doc[key] = getattr(self, key).model_dump(mode="json")
        return doc
