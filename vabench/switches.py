"""Every `VABENCH_*` environment variable: declared once, read through `get`.

A variable is one of three kinds:

- behaviour: how the sweep runs (Warp's substep loop, the JPEG encoder, the caches...);
- measurement: what the sweep measures of itself (profiles, the "host:" lines);
- message: what a parent tells the child processes it starts (their share of the cores, of a
  GPU, the Ray sweep's MPS daemon); never set by hand, except `VABENCH_CORES` to pin a machine.

Each behaviour and measurement switch is also a field of the sweep's config (`field`), so a
run directory says how it was run; its variable overrides the field (`resolve`: the
environment wins). The sweep's parent folds the environment into the config, sets the
config's values in its own environment (`apply`) and gives its child processes the same
variables, so every process reads the same value through `get`. A bad value raises
`SwitchError` naming the variable, the value and what is allowed. A variable set to the empty
string counts as unset.

`python -m vabench.switches` prints the table of docs/SETUP.md ("Environment variables").
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass, field
from typing import Any, Literal

Kind = Literal["behaviour", "measurement", "message"]


class SwitchError(ValueError):
    """A variable's value is not one of those allowed."""

    def __init__(self, variable: str, value: str, allowed: str):
        super().__init__(f"{variable} must be {allowed}, got {value!r}")
        self.variable, self.value, self.allowed = variable, value, allowed


# -- parsers: a raw string to a value, or None when it is not allowed -----------------------


@dataclass(frozen=True)
class OneOf:
    """One of `values` (a value of `aliases` stands for another, for older spellings)."""

    values: tuple[str, ...]
    aliases: Mapping[str, str] = field(default_factory=dict)

    @property
    def allowed(self) -> str:
        return "one of " + ", ".join(self.values)

    def __call__(self, raw: str) -> str | None:
        raw = self.aliases.get(raw, raw)
        return raw if raw in self.values else None


@dataclass(frozen=True)
class Whole:
    minimum: int = 1

    @property
    def allowed(self) -> str:
        return f"a whole number >= {self.minimum}"

    def __call__(self, raw: str) -> int | None:
        try:
            value = int(raw)
        except ValueError:
            return None
        return value if value >= self.minimum else None


@dataclass(frozen=True)
class Seconds:
    positive: bool = False

    @property
    def allowed(self) -> str:
        return f"a number of seconds {'> 0' if self.positive else '>= 0'}"

    def __call__(self, raw: str) -> float | None:
        try:
            value = float(raw)
        except ValueError:
            return None
        ok = value > 0 if self.positive else value >= 0
        return value if ok and value != float("inf") else None


@dataclass(frozen=True)
class Folder:
    @property
    def allowed(self) -> str:
        return "a folder"

    def __call__(self, raw: str) -> str | None:
        return raw


OFF = "off"


@dataclass(frozen=True)
class Cache:
    """A folder, or `off` (also spelled 0 or none, any case)."""

    @property
    def allowed(self) -> str:
        return "a folder or off"

    def __call__(self, raw: str) -> str | None:
        return OFF if raw.strip().lower() in ("0", "off", "none") else raw


DEVICE = re.compile(r"^(cpu|cuda(:\d+)?)$")


@dataclass(frozen=True)
class Device:
    @property
    def allowed(self) -> str:
        return "cpu, cuda or cuda:N"

    def __call__(self, raw: str) -> str | None:
        return raw if DEVICE.match(raw) else None


@dataclass(frozen=True)
class Flag:
    @property
    def allowed(self) -> str:
        return "1 or 0"

    def __call__(self, raw: str) -> bool | None:
        return {"1": True, "0": False}.get(raw)


@dataclass(frozen=True)
class Text:
    @property
    def allowed(self) -> str:
        return "a name"

    def __call__(self, raw: str) -> str | None:
        return raw


Parser = OneOf | Whole | Seconds | Folder | Cache | Device | Flag | Text


@dataclass(frozen=True)
class Switch:
    env: str
    kind: Kind
    parse: Parser
    default: Any
    """The value when the variable is unset (None: unset, whose meaning `doc` says)."""
    doc: str
    field: str | None = None
    """The config field it overrides ("section.name"); None for a message."""

    @property
    def name(self) -> str:
        """What `get` takes: the variable's name without `VABENCH_`, in lower case."""
        return self.env.removeprefix("VABENCH_").lower()

    def read(self, raw: str) -> Any:
        """The value of the variable set to `raw`; raises `SwitchError`."""
        value = self.parse(raw)
        if value is None:
            raise SwitchError(self.env, raw, self.parse.allowed)
        return value


_DECLARED = (
    # -- behaviour ----------------------------------------------------------------------------
    Switch(
        "VABENCH_WARP_DEVICE",
        "behaviour",
        Device(),
        "cuda:0",
        "the Warp device of physics and images; `cpu` runs them on Warp's CPU device (slow; "
        "for tests)",
        "simulator.warp_device",
    ),
    Switch(
        "VABENCH_WARP_LOOP",
        "behaviour",
        OneOf(("device", "per_step", "unrolled")),
        "device",
        "how a Warp action holds its substeps: `device` (one graph, the substeps in a CUDA "
        "while loop), `per_step` (a graph per substep), `unrolled`",
        "simulator.warp_loop",
    ),
    Switch(
        "VABENCH_CUDA_SYNC",
        "behaviour",
        OneOf(("block", "spin")),
        "block",
        "how threads wait for the GPU: `block` (they sleep on events made with "
        "CU_EVENT_BLOCKING_SYNC), `spin` (CUDA's default: a core spins per waiting thread)",
        "simulator.cuda_sync",
    ),
    Switch(
        "VABENCH_MATMUL_PRECISION",
        "behaviour",
        OneOf(("highest", "high", "default", "float32", "tensorfloat32", "bfloat16")),
        "highest",
        "JAX's float32 matmul precision; `default` restores JAX's (TF32 on recent NVIDIA GPUs)",
        "simulator.matmul_precision",
    ),
    Switch(
        "VABENCH_JAX_CACHE",
        "behaviour",
        Cache(),
        None,
        "JAX's persistent compilation cache (default `~/.cache/vabench/jax`; `off` disables it)",
        "simulator.jax_cache",
    ),
    Switch(
        "VABENCH_STATE_CACHE",
        "behaviour",
        Cache(),
        None,
        "the settled-state cache (default `~/.cache/vabench/settled`; `off` disables it)",
        "simulator.state_cache",
    ),
    Switch(
        "VABENCH_WARP_JPEG",
        "behaviour",
        OneOf(("auto", "kernels", "nvjpeg", "device", "host")),
        "auto",
        "the Warp renderer's JPEG encoder: `auto` (on a GPU its own JPEG kernels, else nvJPEG, "
        "else nvImageCodec, else CPU threads), `kernels`, `nvjpeg`, `device` (nvImageCodec), "
        "`host` (threads)",
        "render.warp_jpeg",
    ),
    Switch(
        "VABENCH_RENDER_CONCURRENCY",
        "behaviour",
        Whole(1),
        1,
        "render requests of one task an engine sends to the Warp renderer side by side",
        "render.concurrency",
    ),
    Switch(
        "VABENCH_WARP_PRECOMPILE",
        "behaviour",
        OneOf(("on", "off", "first"), {"1": "on", "0": "off"}),
        "on",
        "every family's Warp kernels compiled side by side in the background when a sweep "
        "starts on a GPU: `on`, `off` (each family compiles on first use), `first` (every "
        "family waits for the whole compile)",
        "executor.precompile",
    ),
    Switch(
        "VABENCH_CACHE",
        "behaviour",
        Folder(),
        None,
        "the folder of the precompile's markers, `warp_compiled/` (default `~/.cache/vabench`)",
        "executor.cache_dir",
    ),
    # -- measurement --------------------------------------------------------------------------
    Switch(
        "VABENCH_HOSTLOAD_S",
        "measurement",
        Seconds(),
        60.0,
        'seconds between the sweep\'s "host:" log lines (`0` turns them off)',
        "profiling.hostload_s",
    ),
    Switch(
        "VABENCH_PROFILE_DIR",
        "measurement",
        Folder(),
        None,
        "a folder where each worker of `executor: processes` writes a cProfile per chunk",
        "profiling.cprofile_dir",
    ),
    Switch(
        "VABENCH_KERNEL_PROFILE",
        "measurement",
        Folder(),
        None,
        "a folder where each worker of `executor: processes` writes a window of its GPU "
        "kernels (`python -m vabench.tuning.kernel_profile FOLDER` sums them)",
        "profiling.kernel_dir",
    ),
    Switch(
        "VABENCH_KERNEL_PROFILE_AT",
        "measurement",
        Seconds(),
        60.0,
        "seconds after a worker's chunk starts that its kernel window begins",
        "profiling.kernel_at_s",
    ),
    Switch(
        "VABENCH_KERNEL_PROFILE_S",
        "measurement",
        Seconds(positive=True),
        20.0,
        "seconds of the kernel window",
        "profiling.kernel_s",
    ),
    Switch(
        "VABENCH_PRECOMPILE_STATS",
        "measurement",
        Folder(),
        None,
        "a folder where each precompile child writes what it compiled (default: a temporary one)",
        "profiling.precompile_stats",
    ),
    # -- messages from a parent to its children -----------------------------------------------
    Switch(
        "VABENCH_CORES",
        "message",
        Whole(1),
        None,
        "the cores a process sizes its pools for (default: the CPUs it may use); the sweep "
        "gives each worker its share; the test suite pins it",
    ),
    Switch(
        "VABENCH_GPU_SHARE",
        "message",
        Whole(1),
        1,
        "how many processes share each GPU (GPU buffers sized from the memory free take that "
        "share of it)",
    ),
    Switch(
        "VABENCH_RAY_MPS",
        "message",
        Text(),
        None,
        "a Ray sweep's id, under which its engines that share GPUs join their node's CUDA MPS "
        "daemon",
    ),
    Switch(
        "VABENCH_RAY_MPS_RANKED",
        "message",
        Flag(),
        False,
        "`1`: the Ray sweep has a critical path, whose engines are its GPUs' normal MPS clients",
    ),
)

SWITCHES: dict[str, Switch] = {s.name: s for s in _DECLARED}
"""Every switch by name (`Switch.name`), in the table's order."""
BY_FIELD: dict[str, Switch] = {s.field: s for s in _DECLARED if s.field is not None}
"""The behaviour and measurement switches by config field."""


def variable(name: str) -> str:
    """The environment variable of switch `name`."""
    return SWITCHES[name].env


def is_set(name: str, environ: Mapping[str, str] = os.environ) -> bool:
    return bool(environ.get(SWITCHES[name].env, "").strip())


def get(name: str, environ: Mapping[str, str] = os.environ) -> Any:
    """Switch `name`'s value in `environ`, or its default where unset; raises `SwitchError`
    for a value that is not allowed (KeyError for an undeclared name)."""
    switch = SWITCHES[name]
    if not is_set(name, environ):
        return switch.default
    return switch.read(environ[switch.env].strip())


def value(name: str, configured: Any, environ: Mapping[str, str] = os.environ) -> tuple[Any, bool]:
    """The precedence, in one place: (the environment's value, True) where its variable is set,
    else (the config's `configured`, False)."""
    if is_set(name, environ):
        return get(name, environ), True
    return configured, False


@dataclass(frozen=True)
class Effective:
    """The switches a sweep runs with (`resolve`)."""

    values: Mapping[str, Any]
    """Every switch's value by name: the behaviour and measurement switches as the config
    and environment decide them, the messages as this process reads them."""
    from_environment: tuple[str, ...] = ()
    """The switches whose variable overrode the config's field."""

    def overrides(self) -> list[str]:
        """`field=value (VARIABLE)` for each switch the environment overrode."""
        return [
            f"{SWITCHES[n].field}={as_text(self.values[n])} ({SWITCHES[n].env})"
            for n in self.from_environment
        ]


def resolve(configured: Mapping[str, Any], environ: Mapping[str, str] = os.environ) -> Effective:
    """The effective switches of a config whose fields hold `configured` (by switch name; a
    missing one is its default). Raises `SwitchError` for the first bad value."""
    values, from_env = {}, []
    for name, switch in SWITCHES.items():
        if switch.field is None:
            values[name] = get(name, environ)
            continue
        values[name], overridden = value(name, configured.get(name, switch.default), environ)
        if overridden:
            from_env.append(name)
    return Effective(values, tuple(from_env))


def current(environ: Mapping[str, str] = os.environ) -> dict[str, Any]:
    """Every switch's value as a process with `environ` reads it."""
    return {name: get(name, environ) for name in SWITCHES}


def as_text(value: Any) -> str:
    """`value` as its variable spells it (what `Switch.read` reads back)."""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def environment(values: Mapping[str, Any]) -> dict[str, str]:
    """The variables that carry `values` of the behaviour and measurement switches to another
    process: those that differ from their default (an unset variable means the default)."""
    return {
        SWITCHES[n].env: as_text(v)
        for n, v in values.items()
        if SWITCHES[n].field is not None and v is not None and v != SWITCHES[n].default
    }


def apply(
    values: Mapping[str, Any], environ: MutableMapping[str, str] = os.environ
) -> dict[str, str]:
    """Set in `environ` (this process's, inherited by the processes it starts) the variables
    of `environment(values)` that it does not set already; returns those set."""
    added = {k: v for k, v in environment(values).items() if not environ.get(k, "").strip()}
    environ.update(added)
    return added


# -- the table of docs/SETUP.md ----------------------------------------------------------------


def table() -> str:
    """The Markdown table of every variable: kind, config field, default, values, meaning."""
    lines = [
        "| variable | kind | config field | default | values | what it does |",
        "|---|---|---|---|---|---|",
    ]
    for s in SWITCHES.values():
        default = "unset" if s.default is None else f"`{as_text(s.default)}`"
        where = f"`{s.field}`" if s.field else "(environment only)"
        lines.append(
            f"| `{s.env}` | {s.kind} | {where} | {default} | {s.parse.allowed} | {s.doc} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
