"""Reading a sweep config file: YAML with positions, overrides from the command line, and
one `SweepConfigError` listing every problem in the order the file reads.

The old spelling of the physics backend, `simulator: {backend: mjx, impl: warp | jax}`, is read
as the one-word name it means (`backend: warp | mjx`, `sim_mjx.backends.backend_name`), with one
warning naming the file, the field and what to write instead; the resolved config, and so the
run directory's sweep.yaml, holds the new spelling only.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from vabench import switches
from vabench.config.problems import Problem, SweepConfigError, pydantic_problems, yaml_problem
from vabench.config.resolve import (
    model_problems,
    resolve_seeds,
    resolve_tasks,
    resolve_tracks,
    server_problems,
)
from vabench.config.schema import (
    EMBEDDED,
    EMBEDDED_PLACEHOLDER_URL,
    SweepConfig,
    SweepFile,
    suite_tasks,
)
from vabench.llm_pool.server_config import ServerConfig
from vabench.sim_mjx.backends import BACKENDS, backend_name
from vabench.switches import SWITCHES, SwitchError

log = logging.getLogger(__name__)


def load_config(
    path: Path | str,
    *,
    environ: Mapping[str, str] = os.environ,
    overrides: Mapping[str, Any] | None = None,
    require_keys: bool = True,
    edit: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
) -> SweepConfig:
    """Read, check and resolve the sweep config at `path`.

    `overrides` replace values of the document before it is checked; keys are dotted field
    paths (`out`, `executor.kind`), as the command line sets them. `environ` is where the
    models' `api_key_env` variables must be set (and non-empty), unless `require_keys` is false
    (`--dry-run`, which warns of them instead: `keys.KeySources.unset`), and where the
    `VABENCH_*` variables that override config fields are read (`vabench.switches`). `edit`
    rewrites the document after the overrides, before it is checked (the command line's
    quick-trial flags, `config.overrides`, which edit lists such as `models:`).

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
        raise SweepConfigError(file, [yaml_problem(err)]) from None
    except yaml.YAMLError as err:
        raise SweepConfigError(file, [Problem("", f"YAML error: {err}")]) from None
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise SweepConfigError(
            file, [Problem("", f"expected a mapping of settings, got {type(doc).__name__}")]
        )
    doc = _apply_overrides(doc, overrides or {})
    if edit is not None:
        doc = edit(doc)
    doc, old_spelling = _old_physics_spelling(doc, file)
    config, problems = _check(doc, path.stem, environ if require_keys else None)
    if config is not None:
        config, problems = _with_environment(config, environ)
    problems = old_spelling + problems
    if problems or config is None:
        order = {key: i for i, key in enumerate(doc)}  # report in the order the file reads
        problems.sort(key=lambda p: _position(p.path, order))
        raise SweepConfigError(file, problems)
    return config


def _with_environment(
    config: SweepConfig, environ: Mapping[str, str]
) -> tuple[SweepConfig | None, list[Problem]]:
    """`config` with the fields whose `VABENCH_*` variable `environ` sets overridden by it
    (`vabench.switches.value`: the environment wins); a problem for each bad value."""
    problems, overridden = [], {}
    for name, configured in config.switch_values().items():
        field = str(SWITCHES[name].field)
        try:
            value, from_env = switches.value(name, configured, environ)
        except SwitchError as err:
            problems.append(Problem(field, f"{err} (the variable overrides this field)"))
            continue
        if not from_env:
            continue
        try:  # the field's own checks too (a declaration that disagrees with its field)
            config.with_switch_values({name: value})
        except ValidationError as err:
            message = "; ".join(e["msg"] for e in err.errors())
            problems.append(Problem(field, f"{SWITCHES[name].env}={value!r}: {message}"))
            continue
        overridden[name] = value
    if problems:
        return None, problems
    return config.with_switch_values(overridden), []


def _old_physics_spelling(doc: dict[str, Any], file: str) -> tuple[dict[str, Any], list[Problem]]:
    """The document with `simulator.impl` (deprecated) folded into `simulator.backend`, logging
    what to write instead; a problem when the two contradict or impl is no impl."""
    sim = doc.get("simulator")
    if not isinstance(sim, dict) or "impl" not in sim:
        return doc, []
    sim = dict(sim)
    impl = sim.pop("impl")
    backend = sim.get("backend", "auto")
    doc = {**doc, "simulator": sim}
    if not isinstance(backend, str) or backend not in BACKENDS:
        return doc, []  # the schema names the bad backend
    try:
        name = backend_name(backend, impl)
    except ValueError as err:
        names = ", ".join(BACKENDS)
        return doc, [Problem("simulator.impl", f"{err}; impl is deprecated: write {names} alone")]
    sim["backend"] = name
    log.warning(
        "%s: simulator.impl is deprecated: write simulator: {backend: %s} instead of "
        "{backend: %s, impl: %s}%s",
        file,
        name,
        backend,
        impl,
        " (or backend: auto, which runs C MuJoCo where Warp cannot run)"
        if impl == "auto" and name != backend
        else "",
    )
    return doc, []


def _position(path: str, order: Mapping[str, int]) -> tuple[int, int]:
    """Where a problem's field is in the file: its section, then its list entry."""
    match = re.match(r"([^.\[]*)(?:\[(\d+)\])?", path)
    head, index = (match.group(1), match.group(2)) if match else (path, None)
    return order.get(head, len(order)), -1 if index is None else int(index)


def _check(
    doc: dict[str, Any], stem: str, environ: Mapping[str, str] | None
) -> tuple[SweepConfig | None, list[Problem]]:
    """Validate the document; every section is checked even when another one fails (the key
    variables only with an `environ`)."""
    problems: list[Problem] = []
    doc, embedded = _mark_embedded(doc)
    parsed: SweepFile | None = None
    try:
        parsed = SweepFile.model_validate(doc)
    except ValidationError as err:
        problems += pydantic_problems(err, SweepFile)
    problems += model_problems(doc.get("models"), environ)
    problems += server_problems(doc.get("embedded_server"))
    tasks, task_problems = resolve_tasks(doc.get("tasks", "base"))
    problems += task_problems
    tracks, track_problems = resolve_tracks(doc, tasks)
    problems += track_problems
    planned: dict[str, None] = {}
    for track in tracks:
        planned.update(dict.fromkeys(suite_tasks(track.suite, tasks)))
    seeds, seed_problems = resolve_seeds(doc.get("seeds", "verified"), list(planned))
    if not task_problems and not track_problems:  # else they would only repeat those
        problems += seed_problems
    executor = doc.get("executor")
    if isinstance(executor, dict) and executor.get("address") and executor.get("kind") != "ray":
        problems.append(Problem("executor.address", "only used with kind: ray"))
    elif isinstance(executor, dict) and str(executor.get("address")).startswith("ray://"):
        problems.append(
            Problem(
                "executor.address",
                "Ray Client (ray://) cannot carry the records the engines stream to the "
                "driver; run the sweep on a node of the cluster with address: auto (README, "
                '"Multi-machine sweeps")',
            )
        )
    if isinstance(executor, dict) and executor.get("actors") and executor.get("kind") != "ray":
        problems.append(Problem("executor.actors", "only used with kind: ray"))
    if parsed is not None:
        problems += _cap_problems(parsed, embedded)
    if problems or parsed is None:
        return None, problems
    name = parsed.name or stem
    # The sections checked by the schema alone go over as they are; the rest was resolved here.
    as_written = (
        "learning",
        "runs",
        "step_budget",
        "simulator",
        "render",
        "executor",
        "retries",
        "limits",
        "report",
        "records",
        "profiling",
    )
    config = SweepConfig(
        **{key: getattr(parsed, key) for key in as_written},
        name=name,
        out=parsed.out or f"runs/{name}",
        models=tuple(parsed.models),
        embedded_models=tuple(embedded),
        embedded_server=parsed.embedded_server or ServerConfig(),
        tracks=tuple(tracks),
        tasks=tuple(tasks),
        seeds=seeds,
    )
    return config, []


def _cap_problems(parsed: SweepFile, embedded: list[str]) -> list[Problem]:
    """A spend cap counts dollars: every model it covers needs prices (the embedded server's
    models cost nothing without them)."""
    problems = []
    models = parsed.models
    unpriced = [
        (i, m.name) for i, m in enumerate(models) if m.prices is None and m.name not in embedded
    ]
    for i, name in unpriced:
        if models[i].limits.max_cost_usd is not None:
            problems.append(
                Problem(
                    f"models[{i}].limits.max_cost_usd",
                    f"max_cost_usd needs prices for model {name!r} (models[{i}].prices)",
                )
            )
    if parsed.limits.max_cost_usd is not None and unpriced:
        names = ", ".join(repr(n) for _, n in unpriced)
        fields = ", ".join(f"models[{i}].prices" for i, _ in unpriced)
        message = f"max_cost_usd needs prices for model {names} ({fields})"
        problems.append(Problem("limits.max_cost_usd", message))
    return problems


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
