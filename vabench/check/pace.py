"""The dry run's wall time and disk: what earlier sweeps on this machine measured.

Kept per machine and per model kind (`model_kind`: the embedded server's policy, or an API
model): each sweep's end writes its run directory's pace and its records' size, by kind, to
`pace_file()` (the user's cache, keyed by host name), so a dry run reads the pace of the same
kind of model on this machine wherever `--out` points; a random-action pace is never applied
to a paid model. The dry run shows an expected time (the episodes left at the decisions an
episode measured for that kind) beside the upper bound (each at its whole budget), and the
disk the run directory will take (MB an episode measured for that kind) against the free
disk; where this machine has measured no such kind it says so, and for an API model that
the endpoint check has timed here (`vabench.check.latency`) gives the longest wall time at the
check's latency within the models' concurrency and rpm.

A pace is decisions (steps) per second of episode time: the steps of the recorded episodes
over the union of their `[started_at, started_at + wall_s]` intervals, so the pauses between a
stopped sweep and its resumption do not count, and neither do learning sessions. It is a
guide, not a promise: another size or number of episodes in flight changes it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from vabench.check.latency import CheckLatency, api_kind
from vabench.config import SweepConfig
from vabench.machine_cache import cache_dir, read_host, write_host
from vabench.run_layout import EPISODES, RESULTS


def _union_length(intervals: Iterable[tuple[float, float]]) -> float:
    total, end = 0.0, float("-inf")
    for a, b in sorted(intervals):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    if minutes < 1:
        return f"{max(1, round(seconds))} s"
    if minutes < 60:
        return f"{minutes} min"
    return f"{minutes // 60} h {minutes % 60:02d} min"


# -- the pace kept per machine and per model kind ------------------------------------------

DISK_MARGIN = 1.2
"""The dry run warns where the free disk holds less than this times the estimate."""


def pace_file() -> Path:
    """Where this user's measured paces live (every host's, keyed by host name)."""
    return cache_dir() / "pace.json"


def model_kind(config: SweepConfig, model: str) -> str:
    """What decides a model's pace and its records' size: the embedded server's policy, or
    the API and provider model (a random-action pace says nothing of a paid model), and the
    image size (rendering time, MB an episode)."""
    if model in config.embedded_models:
        size = f"{config.render.width}x{config.render.height}"
        return f"embedded {config.embedded_server.policy} at {size}"
    return api_kind(config, model)


@dataclass(frozen=True)
class KindPace:
    """One model kind's pace and record size on one machine, from one run directory."""

    kind: str
    run_dir: str
    episodes: int
    decisions: int
    busy_s: float
    bytes_per_episode: float
    frames: str
    finished_at: float
    task_seconds: dict[str, float] = field(default_factory=dict)
    """The mean seconds an episode of each task took (`wall_s`): what the sweep's driver deals
    its chunks by (`sweep.cells.episode_costs`)."""

    @property
    def decisions_per_s(self) -> float:
        return self.decisions / self.busy_s if self.busy_s > 0 else 0.0

    @property
    def decisions_per_episode(self) -> float:
        return self.decisions / self.episodes if self.episodes else 0.0


def _tree_bytes(path: Path) -> int:
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):
                total += os.stat(os.path.join(root, name)).st_size
    return total


def measure_kinds(run_dir: Path, config: SweepConfig) -> list[KindPace]:
    """The pace and bytes an episode of each model kind of `config` in `run_dir`'s ledger."""
    records: dict[str, list[dict[str, Any]]] = {}
    with contextlib.suppress(OSError, UnicodeDecodeError):
        for line in (run_dir / RESULTS).read_text(encoding="utf-8").splitlines():
            with contextlib.suppress(ValueError):
                record = json.loads(line)
                records.setdefault(str(record.get("model")), []).append(record)
    by_kind: dict[str, list[tuple[str, dict[str, Any]]]] = {}
    for m in config.models:
        for record in records.get(m.name, []):
            by_kind.setdefault(model_kind(config, m.name), []).append((m.name, record))
    out = []
    for kind, pairs in by_kind.items():
        intervals, decisions = [], 0
        walls: dict[str, list[float]] = {}
        for _, r in pairs:
            start, wall = r.get("started_at"), r.get("wall_s")
            if isinstance(start, int | float) and isinstance(wall, int | float) and wall > 0:
                intervals.append((float(start), float(start) + float(wall)))
                decisions += int(r.get("steps_used") or 0)
                walls.setdefault(str(r.get("task")), []).append(float(wall))
        busy = _union_length(intervals)
        if not intervals or decisions == 0 or busy <= 0:
            continue
        models = {name for name, _ in pairs}
        size = sum(_tree_bytes(run_dir / EPISODES / name) for name in models)
        out.append(
            KindPace(
                kind,
                str(run_dir),
                len(intervals),
                decisions,
                busy,
                size / len(pairs),
                config.records.frames,
                max(e for _, e in intervals),
                {task: sum(w) / len(w) for task, w in sorted(walls.items())},
            )
        )
    return out


def keep_pace(run_dir: Path, config: SweepConfig, path: Path | None = None) -> None:
    """Write `run_dir`'s measured kinds to this machine's entries of the pace file (the
    latest measurement of a kind replaces the one before). Never fails a sweep."""
    path = path or pace_file()
    measured = measure_kinds(Path(run_dir), config)
    if not measured:
        return
    write_host(path, {k.kind: asdict(k) for k in measured})


def machine_paces(path: Path | None = None) -> dict[str, KindPace]:
    """This machine's measured kinds (empty where none)."""
    try:
        return {kind: KindPace(**v) for kind, v in read_host(path or pace_file()).items()}
    except TypeError:  # an entry of another version's fields
        return {}


def measured_seconds(
    config: SweepConfig, tasks: Iterable[str], paces: Mapping[str, KindPace]
) -> dict[str, float]:
    """The seconds an episode of each of `tasks` took in this machine's latest sweep of the
    config's model kinds (`paces`, `KindPace.task_seconds`; the mean over kinds), where one
    measured it."""
    kinds = {model_kind(config, m.name) for m in config.models}
    mine = [p.task_seconds for kind, p in paces.items() if kind in kinds]
    measured = {}
    for task in sorted(set(tasks)):
        seen = [seconds[task] for seconds in mine if task in seconds]
        if seen:
            measured[task] = sum(seen) / len(seen)
    return measured


def latency_line(
    config: SweepConfig,
    kind: str,
    models: Sequence[str],
    budgets: Sequence[int],
    check: CheckLatency,
) -> str:
    """The longest wall time of a kind no sweep has measured here, from the endpoint check's
    latency: every decision at that latency, as many calls at once as the models' concurrency
    and the episodes in flight allow, no more a second than their rpm."""
    per_s = 0.0
    for name in models:
        limits = config.model(name).limits
        at_once = min(limits.max_concurrency, config.executor.max_episodes)
        rate = at_once / max(check.latency_s, 1e-3)
        per_s += rate if limits.rpm is None else min(rate, limits.rpm / 60)
    bound = "rpm" if any(config.model(n).limits.rpm for n in models) else "concurrency"
    return (
        f"wall time ({kind}): at most {_duration(sum(budgets) / per_s)} if every episode uses "
        f"its whole budget, at the endpoint check's {check.latency_s:.1f} s a decision "
        f"({check.when}) and {per_s:.2g} decisions a second (the models' limits: {bound}); "
        "no measured pace of this model kind on this machine yet, so no expected time (a "
        "short run of it measures one, e.g. --limit 4)"
    )


def estimate_lines(
    config: SweepConfig,
    left: Mapping[str, Sequence[int]],
    run_dir: Path,
    paces: Mapping[str, KindPace],
    checked: Mapping[str, CheckLatency] | None = None,
) -> tuple[list[str], list[str]]:
    """(lines, warnings) of the dry run: per model kind with episodes `left` (their step
    budgets, by model), the expected and longest wall time at this machine's pace of that
    kind (or, for an API model without one, the longest at the endpoint check's latency,
    `checked`), and the disk the run directory takes against the free disk where it lies."""
    lines, warnings = [], []
    kinds: dict[str, list[int]] = {}
    kind_models: dict[str, list[str]] = {}
    for model, budgets in left.items():
        kinds.setdefault(model_kind(config, model), []).extend(budgets)
        kind_models.setdefault(model_kind(config, model), []).append(model)
    need_bytes = 0.0
    unmeasured_disk = []
    for kind, budgets in sorted(kinds.items()):
        if not budgets:
            continue
        pace = paces.get(kind)
        check = (checked or {}).get(kind)
        if (pace is None or pace.decisions_per_s <= 0) and check is not None:
            lines.append(latency_line(config, kind, kind_models[kind], budgets, check))
            unmeasured_disk.append(kind)
            continue
        if pace is None or pace.decisions_per_s <= 0:
            lines.append(
                f"wall time ({kind}): no measured pace of this model kind on this machine yet "
                "(a short run of it measures one, e.g. --limit 4)"
            )
            unmeasured_disk.append(kind)
            continue
        expected = len(budgets) * min(pace.decisions_per_episode, max(budgets))
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(pace.finished_at))
        lines.append(
            f"wall time ({kind}): about {_duration(expected / pace.decisions_per_s)} expected "
            f"({len(budgets):,} episodes at the {pace.decisions_per_episode:.1f} decisions an "
            f"episode measured), at most {_duration(sum(budgets) / pace.decisions_per_s)} if "
            f"every episode uses its whole budget; pace {pace.decisions_per_s:.2g} decisions "
            f"a second, {pace.episodes:,} episodes in {pace.run_dir}, the last ended {when}"
        )
        per_episode = pace.bytes_per_episode
        if pace.frames != config.records.frames:
            unmeasured_disk.append(kind)  # another frames setting: its size says little
            continue
        need_bytes += per_episode * len(budgets)
    free = _free_bytes(run_dir)
    if need_bytes:
        per = ", ".join(
            f"{paces[k].bytes_per_episode / 1e6:.1f} MB an episode of {k}"
            for k in sorted(kinds)
            if k in paces and k not in unmeasured_disk
        )
        where = f"; {free / 1e9:.1f} GB free there" if free is not None else ""
        lines.append(
            f"disk: about {_size(need_bytes)} for the run directory ({per}; records.frames: "
            f"{config.records.frames}){where}"
        )
        if free is not None and free < DISK_MARGIN * need_bytes:
            warnings.append(
                f"warning: disk: the run directory needs about {_size(need_bytes)} and "
                f"{_existing(run_dir)} has {_size(free)} free; point --out at a larger disk "
                "or keep fewer frames (records.frames: failed or none)"
            )
    if unmeasured_disk:
        lines.append(
            f"disk: not measured for {', '.join(unmeasured_disk)} at records.frames: "
            f"{config.records.frames} (the suite's images take about 6 MB an episode at "
            "1280x960 with every frame kept)"
        )
    return lines, warnings


def _existing(path: Path) -> Path:
    """`path` or its nearest existing parent (a run directory not made yet)."""
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _free_bytes(path: Path) -> float | None:
    try:
        return float(shutil.disk_usage(_existing(path)).free)
    except OSError:
        return None


def _size(n: float) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e9 else f"{n / 1e6:.0f} MB"
