"""A leaderboard: the models of several sweeps merged into one report, aggregated exactly as
one sweep's (`build.write_report` over the merged records).

Scores share a table only when what decides them matches (`results_file.COMPARABLE`: the
model-facing protocol's version, tracks, tasks, seeds, budgets, image settings, physics
backend and action timing); each run directory is compared with the first, and a difference
is refused in one line naming the field, or, with `allow_mismatch`, merged with every model of
the differing sweep marked (its rows and results.json's `models[].mismatch` name the fields).

A model may appear in several directories only with disjoint runs (run indices): then its
runs are pooled, as if one sweep had run them all; the same run of a model twice is refused,
since it would count episodes twice.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vabench.report import publication, results_file
from vabench.run_layout import RESULTS
from vabench.run_records import ReportError, Results, load_results

if TYPE_CHECKING:
    from vabench.report.build import ReportOutput


@dataclass(frozen=True)
class Sweep:
    run_dir: Path
    results: Results
    provenance: dict[str, Any]

    @property
    def models(self) -> set[str]:
        return {r.result.model for r in self.results.scored + self.results.unscored}

    def runs(self, model: str) -> set[int]:
        return {
            r.result.run
            for r in self.results.scored + self.results.unscored
            if r.result.model == model
        }


def run_dirs(paths: Sequence[Path]) -> list[Path]:
    """Each path that holds a results.jsonl, or each child of it that does (a directory of
    runs), in the order given (children by name)."""
    out: list[Path] = []
    for path in paths:
        if (path / RESULTS).is_file():
            out.append(path)
            continue
        children = (
            sorted(p for p in path.iterdir() if (p / RESULTS).is_file()) if path.is_dir() else []
        )
        if not children:
            raise ReportError(f"{path}: no {RESULTS} in it nor in a directory under it")
        out += children
    return out


def _short(value: Any) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 60 else text[:57] + "..."


def differences(first: dict[str, Any], other: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    a, b = first["comparability"], other["comparability"]
    return [(k, a.get(k), b.get(k)) for k in results_file.COMPARABLE if a.get(k) != b.get(k)]


def load_sweeps(paths: Sequence[Path]) -> list[Sweep]:
    sweeps = []
    for path in run_dirs(paths):
        results = load_results(path)
        records = results.scored + results.unscored
        sweeps.append(Sweep(path, results, results_file.provenance(path, records)))
    return sweeps


def merge(sweeps: Sequence[Sweep], allow_mismatch: bool = False) -> tuple[Results, dict[str, str]]:
    """The sweeps' records as one `Results`, and model -> the fields its sweep differs in from
    the first (only with `allow_mismatch`; otherwise a difference raises `ReportError`)."""
    first = sweeps[0]
    marks: dict[str, str] = {}
    for sweep in sweeps[1:]:
        diff = differences(first.provenance, sweep.provenance)
        if diff and not allow_mismatch:
            name, a, b = diff[0]
            more = f" (and {', '.join(d[0] for d in diff[1:])})" if diff[1:] else ""
            raise ReportError(
                f"{sweep.run_dir} is not comparable with {first.run_dir}: {name} differs, "
                f"{_short(a)} vs {_short(b)}{more}; pass --allow-mismatch to merge it marked"
            )
        for model in sweep.models:
            if diff:
                marks[model] = ", ".join(d[0] for d in diff)
    seen: dict[str, tuple[Path, set[int]]] = {}
    for sweep in sweeps:
        for model in sorted(sweep.models):
            runs = sweep.runs(model)
            if model in seen:
                where, before = seen[model]
                if overlap := before & runs:
                    raise ReportError(
                        f"model {model!r} has run(s) {sorted(overlap)} in both {where} and "
                        f"{sweep.run_dir}: a model's runs in several sweeps must be disjoint "
                        "to be pooled"
                    )
                seen[model] = (where, before | runs)
            else:
                seen[model] = (sweep.run_dir, runs)
    merged = Results(first.results.path)
    for sweep in sweeps:
        merged.scored += sweep.results.scored
        merged.unscored += sweep.results.unscored
        merged.truncated_tail |= sweep.results.truncated_tail
        for key, n in sweep.results.retried.items():
            merged.retried[key] = merged.retried.get(key, 0) + n
    return merged, marks


def profiles(sweeps: Sequence[Sweep]) -> list[publication.Profile]:
    """Every sweep's capability profiles (each from its own annotations)."""
    from vabench.report.build import load_diagnostics

    out: list[publication.Profile] = []
    for sweep in sweeps:
        out += publication.profiles(load_diagnostics(sweep.run_dir))
    return out


def generate_board(paths: Sequence[Path], out: Path, allow_mismatch: bool = False) -> ReportOutput:
    """Merge the sweeps under `paths` and write their report to `out`."""
    from vabench.report.build import (
        Board,
        reference_wanted,
        sweep_alerts,
        task_arms,
        task_meta,
        write_report,
    )

    sweeps = load_sweeps(paths)
    merged, marks = merge(sweeps, allow_mismatch)
    board = Board(
        reference=all(reference_wanted(s.run_dir) for s in sweeps),
        profiles=tuple(profiles(sweeps)),
        marks=marks,
        sources=tuple(s.provenance for s in sweeps),
        alerts=tuple(f"{s.run_dir}: {a}" for s in sweeps for a in sweep_alerts(s.results)),
    )
    arms, order, base = task_arms()
    out.mkdir(parents=True, exist_ok=True)
    return write_report(out, merged, arms, order, base, task_meta(), board=board)
